//! Type fingerprints: a publisher and a subscriber must agree on the payload type.
//!
//! The fingerprint hashes the Rust type's full path and its in-memory size, so a renamed or
//! reshaped type is refused with a clear error rather than decoded into garbage. Both ends must
//! therefore share the type from a common crate (as USAL services share `usal-types`).

use serde::{Deserialize, Serialize};

/// Name and fingerprint of a payload type, carried in every declaration.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct TypeInfo {
    /// The Rust type's path, e.g. `usal_types::Position`.
    pub name: String,
    /// A 64-bit hash of the name and the shape.
    pub fingerprint: u64,
}

impl TypeInfo {
    /// The fingerprint of `T`.
    pub fn of<T: 'static>() -> Self {
        let name = std::any::type_name::<T>();
        let size = std::mem::size_of::<T>() as u64;
        let mut h = blake3::Hasher::new();
        h.update(name.as_bytes());
        h.update(&size.to_le_bytes());
        let digest = h.finalize();
        let mut b = [0u8; 8];
        b.copy_from_slice(&digest.as_bytes()[..8]);
        TypeInfo {
            name: name.to_owned(),
            fingerprint: u64::from_le_bytes(b),
        }
    }

    /// Matches any type: what type-agnostic tools (`usal echo`) subscribe with. They receive
    /// raw bytes with the publisher's type name and decode what they know.
    pub fn any() -> Self {
        TypeInfo {
            name: "*".to_owned(),
            fingerprint: 0,
        }
    }

    /// Whether an interest declared with `self` may receive an offer of type `offered`.
    pub fn accepts(&self, offered: &TypeInfo) -> bool {
        self.fingerprint == 0 || self == offered
    }

    /// The info of a function's (arguments, result) pair.
    pub fn of_function<A: 'static, R: 'static>() -> Self {
        let a = Self::of::<A>();
        let r = Self::of::<R>();
        TypeInfo {
            name: format!("fn({}) -> {}", a.name, r.name),
            fingerprint: a.fingerprint.rotate_left(17) ^ r.fingerprint,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distinct_types_have_distinct_fingerprints() {
        assert_ne!(TypeInfo::of::<f64>(), TypeInfo::of::<f32>());
        assert_eq!(TypeInfo::of::<(f64, u8)>(), TypeInfo::of::<(f64, u8)>());
        assert_ne!(
            TypeInfo::of_function::<u8, u16>(),
            TypeInfo::of_function::<u16, u8>()
        );
    }
}
