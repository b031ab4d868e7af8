//! The simulated battery: drained by the time the vehicle is armed and the distance it covers,
//! reported in SYS_STATUS (voltage, current, remaining).
//!
//! Pure: [`Battery::drain`] takes the step's duration and distance. The model is the simplest
//! one that lets a plan's battery rule fire: a constant draw while armed plus an energy cost
//! per kilometre, and a voltage falling linearly from full to empty with the charge.

/// How the battery is sized and drained.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BatteryConfig {
    /// Capacity, mAh.
    pub capacity_mah: f64,
    /// Energy per kilometre covered, Wh/km.
    pub wh_per_km: f64,
    /// Current drawn while armed, whether moving or not, A.
    pub idle_a: f64,
    /// Voltage when full, V.
    pub full_v: f64,
    /// Voltage when empty, V.
    pub empty_v: f64,
}

impl Default for BatteryConfig {
    /// A 3S 5000 mAh pack on a small vehicle.
    fn default() -> Self {
        Self {
            capacity_mah: 5000.0,
            wh_per_km: 5.0,
            idle_a: 0.5,
            full_v: 12.6,
            empty_v: 10.5,
        }
    }
}

/// Why a battery configuration is refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BatteryConfigError {
    /// A value is not a finite number in its range.
    #[error("battery {name} must be {range}, got {value}")]
    OutOfRange {
        /// The setting.
        name: &'static str,
        /// What it must be.
        range: &'static str,
        /// What it was.
        value: f64,
    },
}

impl BatteryConfig {
    /// Checks every value.
    ///
    /// # Errors
    /// The first value out of its range.
    pub fn validate(&self) -> Result<(), BatteryConfigError> {
        let check = |name, range, value: f64, ok: bool| {
            if value.is_finite() && ok {
                Ok(())
            } else {
                Err(BatteryConfigError::OutOfRange { name, range, value })
            }
        };
        check(
            "capacity (mAh)",
            "> 0",
            self.capacity_mah,
            self.capacity_mah > 0.0,
        )?;
        check("Wh/km", ">= 0", self.wh_per_km, self.wh_per_km >= 0.0)?;
        check("idle current (A)", ">= 0", self.idle_a, self.idle_a >= 0.0)?;
        check("empty voltage", "> 0", self.empty_v, self.empty_v > 0.0)?;
        check(
            "full voltage",
            "above the empty voltage",
            self.full_v,
            self.full_v > self.empty_v,
        )
    }
}

/// The battery's state.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Battery {
    cfg: BatteryConfig,
    used_mah: f64,
    current_a: f64,
}

impl Battery {
    /// A full battery.
    pub fn new(cfg: BatteryConfig) -> Self {
        Self {
            cfg,
            used_mah: 0.0,
            current_a: 0.0,
        }
    }

    /// One step of `dt` seconds in which the vehicle covered `distance_m`, armed or not
    /// (a disarmed vehicle draws nothing).
    pub fn drain(&mut self, dt: f64, distance_m: f64, armed: bool) {
        if !(armed && dt.is_finite() && dt > 0.0) {
            self.current_a = 0.0;
            return;
        }
        let distance_m = if distance_m.is_finite() {
            distance_m.max(0.0)
        } else {
            0.0
        };
        // Power for moving: Wh/km × km/h is W.
        let moving_w = self.cfg.wh_per_km * (distance_m / 1000.0) / (dt / 3600.0);
        self.current_a = self.cfg.idle_a + moving_w / self.voltage();
        self.used_mah = (self.used_mah + self.current_a * dt / 3.6).min(self.cfg.capacity_mah);
    }

    /// Charge remaining, 0..=1.
    pub fn fraction(&self) -> f64 {
        (1.0 - self.used_mah / self.cfg.capacity_mah).clamp(0.0, 1.0)
    }

    /// Remaining, whole percent (SYS_STATUS `battery_remaining`).
    pub fn remaining_pct(&self) -> i8 {
        (self.fraction() * 100.0).round() as i8
    }

    /// Voltage, V.
    pub fn voltage(&self) -> f64 {
        self.cfg.empty_v + (self.cfg.full_v - self.cfg.empty_v) * self.fraction()
    }

    /// Current drawn in the last step, A.
    pub fn current(&self) -> f64 {
        self.current_a
    }

    /// Charge used, mAh.
    pub fn used_mah(&self) -> f64 {
        self.used_mah
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_battery_drains_with_time_armed_and_with_distance() {
        let cfg = BatteryConfig {
            capacity_mah: 1000.0,
            wh_per_km: 12.0,
            idle_a: 1.0,
            ..BatteryConfig::default()
        };
        let mut b = Battery::new(cfg);
        assert_eq!(b.remaining_pct(), 100);
        assert!((b.voltage() - 12.6).abs() < 1e-9);
        // Disarmed: nothing drawn.
        b.drain(3600.0, 0.0, false);
        assert_eq!(b.used_mah(), 0.0);
        // Armed and still for 6 minutes at 1 A: 100 mAh.
        for _ in 0..360 {
            b.drain(1.0, 0.0, true);
        }
        assert!((b.used_mah() - 100.0).abs() < 1e-6, "{}", b.used_mah());
        assert_eq!(b.remaining_pct(), 90);
        // Moving costs more than standing still.
        let still = b.current();
        b.drain(1.0, 10.0, true);
        assert!(b.current() > still);
        // 10 m/s at 12 Wh/km is 432 W: about 36 A at 12 V.
        assert!((b.current() - 1.0 - 432.0 / b.voltage()).abs() < 1.0);
        // Runs down to empty and stays there.
        for _ in 0..10_000 {
            b.drain(1.0, 10.0, true);
        }
        assert_eq!(b.remaining_pct(), 0);
        assert!((b.voltage() - 10.5).abs() < 1e-9);
    }

    #[test]
    fn bad_settings_are_refused() {
        assert_eq!(BatteryConfig::default().validate(), Ok(()));
        for bad in [
            BatteryConfig {
                capacity_mah: 0.0,
                ..BatteryConfig::default()
            },
            BatteryConfig {
                wh_per_km: f64::NAN,
                ..BatteryConfig::default()
            },
            BatteryConfig {
                full_v: 10.0,
                ..BatteryConfig::default()
            },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
    }
}
