//! The insiders of names and gateways, shared by `tests/hostile.rs` and
//! `benches/security/hostile.rs`: a sealed domain (the domain key, an identity key per node,
//! a roster binding each key to its namespace and node name, one key listed as the gateways'
//! as `usal run` lists its `gateway.id`, and one for any namespace as its `tools.id`), a
//! victim `rover1/vas` whose `<access>` lets only
//! `ground/*` call it, and insiders holding the domain key and an identity of their own who
//! try to take the victim's fresh callers: by running as the victim's name (`squat`), or by
//! announcing themselves gateways and forwarding a provider of the victim's names from a LAN
//! of their own (`gateway_forgery`). Every node is a real process; every caller is a fresh
//! `marea-probe call` that first knows every peer there is (`--wait-peers`), so it chooses
//! among all the providers it would ever see. Each scene returns how many callers an
//! attacker answered (the attackers are victims of their own, which report the calls they
//! executed) and how many the genuine victim did.

use std::path::PathBuf;
use std::time::Duration;

use marea::identity::{IdentityKey, Listing, Roster};
use marea::protocol::Message;
use serde_json::Value;

use super::{keygen, outcome, probe_with_config, victim_cmd, Net, Proc, T};

/// Fresh callers of each scene.
pub const CALLERS: usize = 8;

/// A sealed domain's files, in a directory of their own.
pub struct Domain {
    pub dir: tempfile::TempDir,
    pub key: PathBuf,
    pub roster: PathBuf,
}

/// The identities of the domain, as the roster lists them: `vas` and `fpma` own `rover1` as
/// nodes `vas` and `fpma` only; `ground` owns `ground` (any node); `gateway` may be any node
/// and act as a gateway; `tools` may be any node of any namespace but no gateway.
const IDENTITIES: &[(&str, &str, &str, bool)] = &[
    ("vas", "rover1", "vas", false),
    ("fpma", "rover1", "fpma", false),
    ("ground", "ground", "", false),
    ("gateway", "*", "", true),
    ("tools", "*", "", false),
];

impl Domain {
    /// Makes the keys and the roster.
    pub fn new() -> Domain {
        let dir = tempfile::tempdir().expect("tempdir");
        let key = keygen(dir.path(), "domain.key");
        let mut roster = Roster::default();
        for (name, namespaces, nodes, gateway) in IDENTITIES {
            let k = IdentityKey::create_files(&dir.path().join(format!("{name}.id")))
                .expect("an identity key");
            roster.list(Listing {
                key: k.public(),
                namespaces: vec![(*namespaces).to_owned()],
                nodes: nodes.split_whitespace().map(str::to_owned).collect(),
                gateway: *gateway,
            });
        }
        let path = dir.path().join("identities.xml");
        std::fs::write(&path, roster.to_xml()).expect("write the roster");
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o644))
            .expect("chmod the roster");
        Domain {
            dir,
            key,
            roster: path,
        }
    }

    /// `<security>` with identity `identity` (`None`: the domain key only) and the roster.
    pub fn security(&self, identity: Option<&str>) -> String {
        let id = identity.map_or(String::new(), |i| {
            format!(r#" identityFile="{}""#, self.identity(i).display())
        });
        format!(
            r#"<security keyFile="{}"{id} identities="{}"/>"#,
            self.key.display(),
            self.roster.display()
        )
    }

    fn identity(&self, name: &str) -> PathBuf {
        self.dir.path().join(format!("{name}.id"))
    }

    /// A directory of its own for `name`'s files.
    fn subdir(&self, name: &str) -> PathBuf {
        let d = self.dir.path().join(name);
        std::fs::create_dir_all(d.join("inbox")).expect("a node's directory");
        d
    }
}

/// A victim-like provider of `<namespace>/vas/retask` (it reports each call it executes), as
/// node `node` of `namespace` on `net`'s LAN, sealed with identity `identity`, with `inner`
/// (`<access>`) besides. Ready.
fn provider(
    domain: &Domain,
    label: &str,
    (node, namespace): (&str, &str),
    identity: Option<&str>,
    net: &Net,
    inner: &str,
) -> Proc {
    let dir = domain.subdir(label);
    let xml = format!(
        r#"<network node="{node}" namespace="{namespace}" domain="{d}">
  {lan}
  {security}
  {inner}
</network>"#,
        d = net.domain,
        lan = lan(net, "lan"),
        security = domain.security(identity),
    );
    let path = dir.join("network.xml");
    std::fs::write(&path, xml).expect("write network.xml");
    let inbox = dir.join("inbox");
    let mut p = probe_with_config(label, &path, "vas", &[], &victim_cmd(&inbox));
    p.expect_key(T, "ready");
    p
}

/// The `<ethernet>` element of `net`'s LAN, named `name`.
fn lan(net: &Net, name: &str) -> String {
    format!(
        r#"<ethernet name="{name}" bind="127.0.0.1:0" multicast="239.255.77.1:{}" interface="127.0.0.1" heartbeatMs="{}" leaseMs="{}"/>"#,
        net.port, net.heartbeat_ms, net.lease_ms
    )
}

/// A gateway process between the LANs of `nets` (one domain), sealed with identity
/// `identity`; `roster`: whether it keeps the domain's roster (a forger's gateway keeps none,
/// so it takes what its own LAN claims). Ready.
fn gateway(
    domain: &Domain,
    label: &str,
    identity: &str,
    roster: bool,
    nets: [(&Net, &str); 2],
) -> Proc {
    let dir = domain.subdir(label);
    let security = if roster {
        domain.security(Some(identity))
    } else {
        format!(
            r#"<security keyFile="{}" identityFile="{}"/>"#,
            domain.key.display(),
            domain.identity(identity).display()
        )
    };
    let xml = format!(
        r#"<network node="{label}" domain="{d}" gateway="true">
  {a}
  {b}
  {security}
</network>"#,
        d = nets[0].0.domain,
        a = lan(nets[0].0, nets[0].1),
        b = lan(nets[1].0, nets[1].1),
    );
    let path = dir.join("network.xml");
    std::fs::write(&path, xml).expect("write network.xml");
    let mut p = Proc::spawn(
        label,
        env!("CARGO_BIN_EXE_marea-probe"),
        &[
            "--config".to_owned(),
            path.display().to_string(),
            "gateway".to_owned(),
        ],
    );
    p.expect_key(T, "ready");
    p
}

/// The calls a provider reported executing so far (it reports within 50 ms of a change).
fn calls_executed(p: &mut Proc) -> usize {
    latest_report(p)["called"].as_array().map_or(0, Vec::len)
}

/// Who answered the fresh callers.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Answered {
    /// Callers whose call was answered (by anyone: the attackers answer as the victim does).
    pub answered: usize,
    /// Calls the genuine victim executed.
    pub genuine: usize,
    /// Calls an attacker executed.
    pub hijacked: usize,
}

/// [`CALLERS`] fresh callers of `rover1/vas/retask` (node `ground/caller<k>`, proven) on
/// `net`, each knowing the peers named `peers` first (`namespace/node`, once per peer);
/// then who answered them.
fn fresh_callers(
    domain: &Domain,
    net: &Net,
    peers: &[&str],
    victim: &mut Proc,
    attackers: &mut [Proc],
) -> Answered {
    let key = domain.key.to_str().expect("utf-8 path");
    let id = domain.identity("ground");
    let roster = domain.roster.to_str().expect("utf-8 path");
    let mut cmd = vec![
        "call",
        "--name",
        "rover1/vas/retask",
        "--arg",
        "21",
        "--wait-ms",
        "15000",
        "--timeout-ms",
        "3000",
    ];
    for p in peers {
        cmd.extend(["--wait-peer", p]);
    }
    let mut callers: Vec<Proc> = (0..CALLERS)
        .map(|k| {
            net.probe_args(
                &format!("caller{k}"),
                &[
                    "--key-file",
                    key,
                    "--identity-file",
                    id.to_str().expect("utf-8 path"),
                    "--identities",
                    roster,
                    "--namespace",
                    "ground",
                ],
                &cmd,
            )
        })
        .collect();
    let answered = callers
        .iter_mut()
        .map(outcome)
        .filter(|r: &Value| r["ok"] == 42)
        .count();
    let a = Answered {
        answered,
        genuine: calls_executed(victim),
        hijacked: attackers.iter_mut().map(calls_executed).sum(),
    };
    eprintln!("trust: {a:?} of {CALLERS} fresh callers");
    a
}

/// The victim `rover1/vas` (the VAS's identity, calls from `ground/*` only) on `net`.
fn victim(domain: &Domain, net: &Net) -> Proc {
    provider(
        domain,
        "victim",
        ("vas", "rover1"),
        Some("vas"),
        net,
        r#"<access><allow kind="call" item="rover1/vas/*" from="ground/*"/></access>"#,
    )
}

/// Squatters on the victim's LAN, each a provider of `rover1/vas/retask`: the FPMa's key
/// running as node `vas` of `rover1` (a node name its key is not listed for) and the ground
/// station's key claiming namespace `rover1`. (The domain key alone declares nothing where a
/// roster is kept: `tests/auth.rs`.)
pub fn squat(test: &str) -> Answered {
    let domain = Domain::new();
    let net = Net::new(test);
    let mut victim = victim(&domain, &net);
    let mut attackers = vec![
        provider(
            &domain,
            "squat-fpma",
            ("vas", "rover1"),
            Some("fpma"),
            &net,
            "",
        ),
        provider(
            &domain,
            "squat-ground",
            ("vas2", "rover1"),
            Some("ground"),
            &net,
            "",
        ),
    ];
    // The victim and the squatter share a name.
    let peers = ["rover1/vas", "rover1/vas", "rover1/vas2"];
    fresh_callers(&domain, &net, &peers, &mut victim, &mut attackers)
}

/// A self-declared gateway: the victim on LAN `air` behind the domain's gateway, its callers
/// on LAN `ground`; the attacker's gateway (a key listed for any namespace, not as a
/// gateway) joins `ground` to a LAN of its own where a provider of `rover1/vas/retask` runs.
pub fn gateway_forgery(test: &str) -> Answered {
    let domain = Domain::new();
    let ground = Net::new(test);
    let air = Net::new(&format!("{test}-air"));
    let evil = Net::new(&format!("{test}-evil"));
    let (air, evil) = (
        Net {
            domain: ground.domain.clone(),
            ..air
        },
        Net {
            domain: ground.domain.clone(),
            ..evil
        },
    );
    let mut victim = victim(&domain, &air);
    let _gateway = gateway(
        &domain,
        "gateway",
        "gateway",
        true,
        [(&air, "air"), (&ground, "ground")],
    );
    let fake = provider(&domain, "fake-vas", ("vas", "rover1"), None, &evil, "");
    let _forger = gateway(
        &domain,
        "forger",
        "tools",
        false,
        [(&evil, "evil"), (&ground, "ground")],
    );
    let mut attackers = vec![fake];
    // Each caller knows the two gateways.
    fresh_callers(
        &domain,
        &ground,
        &["gateway", "forger"],
        &mut victim,
        &mut attackers,
    )
}

/// What an insider forging the station's address, and replaying and reflecting what it read
/// off the LAN, got the victim to take.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Forged {
    /// Calls the victim executed with the forger's argument.
    pub calls_executed: usize,
    /// Samples carrying the forger's marker the victim delivered.
    pub samples_delivered: u64,
    /// Captured frames sent again (replayed as the station's, reflected back to the victim).
    pub replayed: u64,
    /// Of those, the victim's own frames reflected back to it.
    pub reflected: u64,
    /// Of those, how many the victim did not count refused at its seal.
    pub replays_accepted: u64,
    /// Datagrams forged with the domain key as the station's.
    pub forged: u64,
    /// Of those, how many the victim counted refused at its seal.
    pub forged_refused: u64,
    /// The station's positions kept coming (25 more after the attacks, forged `Bye`s as the
    /// station among them), the station still known and pair-sealed.
    pub legit_flowing: bool,
}

/// A position of the forger's: latitude 666 (the victim counts such samples apart), the rest
/// zero, encoded as the probes' `Position` is (three f64, two f32).
fn marked_position() -> Vec<u8> {
    let mut p = 666.0f64.to_le_bytes().to_vec();
    p.resize(32, 0);
    p
}

fn v4(addr: &str) -> std::net::SocketAddrV4 {
    match addr
        .trim_start_matches("udp://")
        .parse()
        .unwrap_or_else(|e| panic!("{addr}: not a UDP address: {e}"))
    {
        std::net::SocketAddr::V4(a) => a,
        other => panic!("{other}: not IPv4"),
    }
}

/// The insider of "Trust that holds inside the domain", item 1: it holds the domain key (no
/// identity), reads what the victim and two proven `ground` nodes exchange (a publisher of
/// positions at 50 Hz, a subscriber of the victim's link health), then (1) sends calls, file
/// offers and marked position samples sealed with the domain key from the publisher's
/// address, (2) replays the publisher's captured frames from its address, and (3) reflects
/// the victim's captured frames to the subscriber back to the victim from the subscriber's
/// address. `None` when this host gives no raw sockets (root or `CAP_NET_RAW`), which
/// forging source addresses takes.
pub fn forged_as_station(test: &str) -> Option<Forged> {
    use marea::link::auth::DomainKey;
    let capture = super::attacker::LoopbackCapture::open()?;
    let domain = Domain::new();
    let net = Net::new(test);
    let mut victim = provider(
        &domain,
        "victim",
        ("vas", "rover1"),
        Some("vas"),
        &net,
        r#"<access>
    <allow kind="call" item="rover1/vas/*" from="ground/*"/>
    <allow kind="publish" item="**" from="ground/*"/>
  </access>"#,
    );
    let target = v4(victim
        .seen
        .iter()
        .find_map(|v| v["addrs"][0].as_str())
        .expect("the victim's address"));
    let (key, id, roster) = (
        domain.key.to_str().expect("utf-8 path").to_owned(),
        domain.identity("ground"),
        domain.roster.to_str().expect("utf-8 path").to_owned(),
    );
    let ground = [
        "--key-file",
        &key,
        "--identity-file",
        id.to_str().expect("utf-8 path"),
        "--identities",
        &roster,
        "--namespace",
        "ground",
    ];
    let _publisher = net.probe_args("gs", &ground, &super::publishing("position"));
    let _subscriber = net.probe_args(
        "monitor",
        &ground,
        &[
            "health",
            "--pattern",
            "rover1/link/*/stats",
            "--count",
            "100000000",
        ],
    );
    let sealed = |r: &Value, who: &str| {
        r["pair_sealed"]
            .as_array()
            .is_some_and(|a| a.iter().any(|p| p == who))
    };
    let samples = |r: &Value| {
        r["samples"]["gs ground/probe/position"]
            .as_u64()
            .unwrap_or(0)
    };
    let r = victim.expect(T, "both ground nodes pair-sealed, positions flowing", |v| {
        v.get("report").is_some_and(|r| {
            sealed(r, "ground/gs") && sealed(r, "ground/monitor") && samples(r) >= 5
        })
    })["report"]
        .clone();
    let (gs, monitor) = (
        v4(r["peer_addrs"]["ground/gs"].as_str().expect("gs's address")),
        v4(r["peer_addrs"]["ground/monitor"]
            .as_str()
            .expect("monitor's address")),
    );
    // Read off the LAN: the publisher's frames to the victim, the victim's to the subscriber
    // (its link health, once a second).
    let from_gs = capture.udp(gs, target, 20, Duration::from_secs(5));
    let to_monitor = capture.udp(target, monitor, 4, Duration::from_secs(10));
    let at_seal = |r: &Value| {
        super::hostile::refusals(r, "auth_rejected")
            + super::hostile::refusals(r, "replay_rejected")
    };
    let base = at_seal(&latest_report(&mut victim));
    let key = DomainKey::load(&domain.key).expect("the domain key");
    let mut as_gs = super::attacker::Forger::spoofing(Some(&key), gs)?;
    let forged_to = std::net::SocketAddr::V4(target);
    as_gs
        .safe(forged_to, &super::hostile::forged_session_traffic())
        .expect("send");
    for id in 1..=24u32 {
        as_gs
            .fast(
                forged_to,
                &Message::Var {
                    id,
                    payload: marked_position(),
                },
            )
            .expect("send");
    }
    let forged = as_gs.sent;
    // Its announcements, sealed with the domain key as every node's are: a Bye as the
    // station, from its address, must not evict it.
    let sniffer = super::attacker::Sniffer::join(net.group()).expect("join the multicast group");
    let (gs_id, _) = sniffer
        .capture_from(std::net::SocketAddr::V4(gs), T)
        .expect("an announcement of the station");
    for _ in 0..5 {
        as_gs
            .discovery(forged_to, &Message::Bye { node_id: gs_id })
            .expect("send");
    }
    let mut replayer = super::attacker::Forger::spoofing(None, gs)?;
    for d in &from_gs {
        replayer.raw(forged_to, d).expect("send");
    }
    let mut reflector = super::attacker::Forger::spoofing(None, monitor)?;
    for d in &to_monitor {
        reflector.raw(forged_to, d).expect("send");
    }
    let replayed = replayer.sent + reflector.sent;
    let wanted = base + forged + replayed;
    let r = victim
        .try_expect(T, |v| v.get("report").is_some_and(|r| at_seal(r) >= wanted))
        .map_or_else(|| latest_report(&mut victim), |v| v["report"].clone());
    let refused = at_seal(&r).saturating_sub(base);
    let executed = r["called"]
        .as_array()
        .map_or(0, |c| c.iter().filter(|c| c.as_u64() != Some(21)).count());
    let before = samples(&r);
    let legit_flowing = victim
        .try_expect(T, |v| {
            v.get("report").is_some_and(|r| {
                samples(r) >= before + 25 && sealed(r, "ground/gs") && r["peers"]["ground/gs"] == 1
            })
        })
        .is_some();
    // The forged datagrams counted first: what is left of the refusals are the replays'.
    let f = Forged {
        legit_flowing,
        reflected: reflector.sent,
        calls_executed: executed,
        samples_delivered: r["marked"].as_u64().unwrap_or(0),
        replayed,
        replays_accepted: replayed.saturating_sub(refused.saturating_sub(forged)),
        forged,
        forged_refused: refused.min(forged),
    };
    eprintln!(
        "trust: forged as the station: {f:?} (captured {} + {})",
        from_gs.len(),
        to_monitor.len()
    );
    Some(f)
}

/// The victim's latest report (waiting a little for one more).
fn latest_report(p: &mut Proc) -> Value {
    let _ = p.try_expect(Duration::from_millis(300), |_| false);
    p.seen
        .iter()
        .rev()
        .find_map(|v| v.get("report"))
        .cloned()
        .unwrap_or(Value::Null)
}
