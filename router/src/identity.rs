//! Zenoh clients calling as themselves.
//!
//! A Zenoh query carries no proof of who sent it, so the bridge cannot tell its clients apart
//! by their queries. The router can: it authenticated each client's session (the user name of
//! Zenoh's user/password authentication, the common name of a mutual-TLS certificate), and its
//! access control filters what each session may send. So a client calls as itself under a key
//! of its own, `usal/<D>/@as/<identity>/<ns>/<service>/<fn>`, and the router lets only the
//! sessions authenticated as `<identity>` query there: this module adds the Zenoh access-control
//! rules that say so, for every identity the router knows, to whatever rules its configuration
//! already has. marea's `<access>` rules see such a call as `zenoh/<identity>`; a call on the
//! plain key `usal/<D>/<ns>/<service>/<fn>` as `zenoh/anonymous`.

use std::path::Path;

use anyhow::{bail, Context};
use serde_json::{json, Value};

/// The namespace marea's `<access>` rules see Zenoh clients in (`from="zenoh/<identity>"`).
pub const NAMESPACE: &str = "zenoh";

/// Who a call on a function's plain key is from: any client, proven or not.
pub const ANONYMOUS: &str = "anonymous";

/// The key chunk under which a client calls as itself (verbatim: no wildcard reaches it).
pub const AS: &str = "@as";

/// Whether `name` can be an identity: one key chunk, no wildcard or verbatim marker, and not
/// the name of the anonymous caller.
pub fn check(name: &str) -> anyhow::Result<()> {
    let bad = name.is_empty()
        || name == ANONYMOUS
        || name.starts_with('@')
        || name.contains(['/', '*', '$', '?', '#']);
    if bad {
        bail!("{name:?} cannot be a Zenoh client's identity: it must be one key chunk (no '/', '*', '$', '?', '#', no leading '@') and not {ANONYMOUS:?}");
    }
    Ok(())
}

/// The user names of a Zenoh user/password dictionary (`user:password` a line, as `zenohd`
/// reads it).
///
/// # Errors
/// The file cannot be read, or a line (named by its number) is no `user:password`.
pub fn dictionary_users(path: &Path) -> anyhow::Result<Vec<String>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading the user dictionary {}", path.display()))?;
    let mut users = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let Some((user, _)) = line.split_once(':') else {
            bail!("{}:{}: expected user:password", path.display(), i + 1);
        };
        users.push(user.to_owned());
    }
    Ok(users)
}

/// The identities of the Zenoh clients of a router with `config`: the users of its
/// user/password dictionary, if it has one, and the certificate names given (`cert_names`).
///
/// # Errors
/// The dictionary cannot be read, or a name cannot be an identity.
pub fn identities(config: &zenoh::Config, cert_names: &[String]) -> anyhow::Result<Vec<String>> {
    let mut names = match config
        .get_json("transport/auth/usrpwd/dictionary_file")
        .ok()
        .and_then(|j| serde_json::from_str::<Option<String>>(&j).ok())
        .flatten()
    {
        Some(file) => dictionary_users(Path::new(&file))?,
        None => Vec::new(),
    };
    names.extend(cert_names.iter().cloned());
    names.sort();
    names.dedup();
    for n in &names {
        check(n)?;
    }
    Ok(names)
}

/// Adds to `config`'s access control (enabled if it was not, allowing what it did not say)
/// the rules that keep `usal/<domain>/@as/<identity>/**` to the sessions authenticated as
/// `<identity>` (by user name or certificate name), for each of `identities`: nobody else's
/// query reaches the bridge there.
///
/// # Errors
/// Zenoh refuses the resulting configuration.
pub fn restrict_calls_as(
    config: &mut zenoh::Config,
    domain: &str,
    identities: &[String],
) -> anyhow::Result<()> {
    let mut acl: Value = config
        .get_json("access_control")
        .ok()
        .and_then(|j| serde_json::from_str(&j).ok())
        .unwrap_or(Value::Null);
    if !acl.get("enabled").and_then(Value::as_bool).unwrap_or(false) {
        acl = json!({"enabled": true, "default_permission": "allow", "rules": [], "subjects": [], "policies": []});
    }
    let rules = calls_as_rules(domain, identities);
    for part in ["rules", "subjects", "policies"] {
        let mine = rules[part].as_array().cloned().unwrap_or_default();
        match acl.get_mut(part).and_then(Value::as_array_mut) {
            Some(theirs) => theirs.extend(mine),
            None => acl[part] = Value::Array(mine),
        }
    }
    config
        .insert_json5("access_control", &acl.to_string())
        .map_err(|e| anyhow::anyhow!("{e}"))
        .context("Zenoh refused the access control for calls made as an identity")
}

/// The rules, subjects and policies of [`restrict_calls_as`]. Zenoh allows a message when
/// one of the subjects a session matches allows it, and a subject's deny rules win over its
/// allow rules: so every session is denied the whole `@as` space, and each identity's
/// sessions are allowed their own part and denied every other identity's.
fn calls_as_rules(domain: &str, identities: &[String]) -> Value {
    let space = |who: &str| format!("usal/{domain}/{AS}/{who}/**");
    let mut rules = vec![json!({
        "id": "usal-as-nobody", "permission": "deny", "flows": ["ingress"],
        "messages": ["query"], "key_exprs": [format!("usal/{domain}/{AS}/**")],
    })];
    let mut subjects = vec![json!({"id": "usal-anyone"})];
    let mut policies = vec![json!({"rules": ["usal-as-nobody"], "subjects": ["usal-anyone"]})];
    for me in identities {
        let others: Vec<String> = identities
            .iter()
            .filter(|o| *o != me)
            .map(|o| space(o))
            .collect();
        let mut mine = vec![format!("usal-as-{me}")];
        rules.push(json!({
            "id": format!("usal-as-{me}"), "permission": "allow", "flows": ["ingress", "egress"],
            "messages": ["query", "reply"], "key_exprs": [space(me)],
        }));
        if !others.is_empty() {
            rules.push(json!({
                "id": format!("usal-as-{me}-not-others"), "permission": "deny", "flows": ["ingress"],
                "messages": ["query"], "key_exprs": others,
            }));
            mine.push(format!("usal-as-{me}-not-others"));
        }
        subjects.push(json!({"id": format!("usal-user-{me}"), "usernames": [me]}));
        subjects.push(json!({"id": format!("usal-cert-{me}"), "cert_common_names": [me]}));
        policies.push(json!({
            "rules": mine,
            "subjects": [format!("usal-user-{me}"), format!("usal-cert-{me}")],
        }));
    }
    json!({"rules": rules, "subjects": subjects, "policies": policies})
}

#[cfg(test)]
mod tests {
    use super::*;

    fn acl(config: &zenoh::Config) -> Value {
        serde_json::from_str(&config.get_json("access_control").unwrap()).unwrap()
    }

    #[test]
    fn the_users_of_a_dictionary_are_its_identities_and_a_bad_line_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let dict = dir.path().join("users.txt");
        std::fs::write(&dict, "pilot:s3cret\n\nguest:pw:with:colons\n").unwrap();
        assert_eq!(dictionary_users(&dict).unwrap(), ["pilot", "guest"]);
        std::fs::write(&dict, "pilot:s3cret\nno-password\n").unwrap();
        let e = dictionary_users(&dict).unwrap_err().to_string();
        assert!(e.ends_with("users.txt:2: expected user:password"), "{e}");

        let mut config = zenoh::Config::default();
        config
            .insert_json5(
                "transport/auth/usrpwd/dictionary_file",
                &serde_json::to_string(&dict).unwrap(),
            )
            .unwrap();
        std::fs::write(&dict, "pilot:a\nguest:b\n").unwrap();
        let names = identities(&config, &["ops.example.org".into(), "pilot".into()]).unwrap();
        assert_eq!(names, ["guest", "ops.example.org", "pilot"]);
    }

    #[test]
    fn a_name_that_is_no_key_chunk_or_is_anonymous_is_refused() {
        let config = zenoh::Config::default();
        for bad in ["", "a/b", "a*", "@admin", "anonymous", "x$y"] {
            let e = identities(&config, &[bad.into()]).unwrap_err().to_string();
            assert!(
                e.contains("cannot be a Zenoh client's identity"),
                "{bad}: {e}"
            );
        }
    }

    #[test]
    fn each_identity_may_query_its_own_space_only_and_nobody_else_any() {
        let mut config = zenoh::Config::default();
        restrict_calls_as(&mut config, "d", &["pilot".into(), "guest".into()]).unwrap();
        let acl = acl(&config);
        assert_eq!(acl["enabled"], true);
        assert_eq!(acl["default_permission"], "allow");
        let rule = |id: &str| {
            acl["rules"]
                .as_array()
                .unwrap()
                .iter()
                .find(|r| r["id"] == id)
                .unwrap_or_else(|| panic!("no rule {id} in {acl}"))
                .clone()
        };
        assert_eq!(rule("usal-as-nobody")["permission"], "deny");
        assert_eq!(
            rule("usal-as-nobody")["key_exprs"],
            json!(["usal/d/@as/**"])
        );
        assert_eq!(
            rule("usal-as-pilot")["key_exprs"],
            json!(["usal/d/@as/pilot/**"])
        );
        assert_eq!(
            rule("usal-as-pilot-not-others")["key_exprs"],
            json!(["usal/d/@as/guest/**"])
        );
        let policy = acl["policies"]
            .as_array()
            .unwrap()
            .iter()
            .find(|p| p["subjects"] == json!(["usal-user-pilot", "usal-cert-pilot"]))
            .cloned()
            .unwrap_or_else(|| panic!("no policy for pilot in {acl}"));
        assert_eq!(
            policy["rules"],
            json!(["usal-as-pilot", "usal-as-pilot-not-others"])
        );
    }

    #[test]
    fn rules_already_configured_are_kept() {
        let mut config = zenoh::Config::default();
        config
            .insert_json5(
                "access_control",
                r#"{enabled: true, default_permission: "deny",
                    rules: [{id: "mine", permission: "allow", flows: ["ingress", "egress"],
                             messages: ["put"], key_exprs: ["demo/**"]}],
                    subjects: [{id: "all"}],
                    policies: [{rules: ["mine"], subjects: ["all"]}]}"#,
            )
            .unwrap();
        restrict_calls_as(&mut config, "d", &["pilot".into()]).unwrap();
        let acl = acl(&config);
        assert_eq!(acl["default_permission"], "deny");
        let ids: Vec<&str> = acl["rules"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|r| r["id"].as_str())
            .collect();
        assert_eq!(ids, ["mine", "usal-as-nobody", "usal-as-pilot"]);
        assert_eq!(acl["policies"].as_array().unwrap().len(), 3);
    }
}
