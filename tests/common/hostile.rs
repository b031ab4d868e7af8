//! The hostile suite, shared by `tests/hostile.rs` and `benches/security/hostile.rs`: a victim
//! node process (`marea-probe victim`, keyed, with `<access>` rules) and a legitimate peer
//! process publishing positions to it, then the attacks of an outsider without the domain key
//! and of an insider with the key but another namespace. Each attack function returns what it
//! sent and how much of it the victim's counters show refused; the tests assert on the victim's
//! observable outputs.
//!
//! A test's scene ([`Scene::start`]) fails at the first wait that ends without what it waits
//! for and at the first attack that is not refused the way it must be. The benchmark's scene
//! ([`Scene::measuring`]) does neither: each wait ends after its bound with whatever the
//! victim counted by then, each failed check counts as an attack that got through, so an
//! attack that slips through lowers `hostile.rejected_ratio` instead of hiding the figure.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use marea::codec::encode_payload;
use marea::link::auth::DomainKey;
use marea::protocol::{
    Declaration, FileOffer, ItemKind, LoggedDeclaration, Message, NodeId, Origin,
};
use marea::typeinfo::TypeInfo;
use serde_json::Value;

use super::attacker::{self, Forger, Sniffer};
use super::{keygen, outcome, probe_with_config, Net, Proc, T};

/// The legitimate peer's position samples as the victim keys them ("publisher name").
pub const LEGIT_SAMPLES: &str = "gs ground/probe/position";
/// The argument attackers' calls carry (the legitimate ones carry 21).
pub const EVIL_ARG: u64 = 666;

/// Attack messages sent and how many of them the victim's counters show refused (each
/// counted at most once: a refusal counted twice cannot hide one not counted).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Tally {
    pub sent: u64,
    pub refused: u64,
}

impl Tally {
    fn add(&mut self, sent: u64, counted: u64) {
        self.sent += sent;
        self.refused += counted.min(sent);
    }

    /// Refused / sent (1.0 when nothing got through).
    pub fn ratio(&self) -> f64 {
        if self.sent == 0 {
            return 1.0;
        }
        self.refused as f64 / self.sent as f64
    }
}

/// The victim, its legitimate peer, and what both share.
pub struct Scene {
    pub net: Net,
    pub dir: tempfile::TempDir,
    pub key: PathBuf,
    pub inbox: PathBuf,
    pub victim: Proc,
    /// The victim's unicast address.
    pub target: SocketAddr,
    pub legit: Proc,
    /// The victim's latest report.
    pub last: Value,
    /// A test's scene (see the module docs), or the benchmark's.
    strict: bool,
}

/// A counter of a report's `refusals`.
pub fn refusals(report: &Value, what: &str) -> u64 {
    report["refusals"][what].as_u64().unwrap_or(0)
}

/// The legitimate peer's samples the victim delivered so far.
pub fn legit_samples(report: &Value) -> u64 {
    report["samples"][LEGIT_SAMPLES].as_u64().unwrap_or(0)
}

fn udp(addr: &str) -> SocketAddr {
    addr.trim_start_matches("udp://")
        .parse()
        .unwrap_or_else(|e| panic!("{addr}: not a UDP address: {e}"))
}

impl Scene {
    /// Starts the victim (`rover1/vas`, calls, files and publications allowed from `ground/*`
    /// only) and the legitimate peer (`ground/gs`, positions at 50 Hz), and waits until the
    /// victim delivers the peer's positions.
    pub fn start(test: &str) -> Scene {
        let net = Net::new(test);
        let dir = tempfile::tempdir().expect("tempdir");
        let key = keygen(dir.path(), "domain.key");
        let inbox = dir.path().join("inbox");
        std::fs::create_dir_all(&inbox).expect("inbox");
        let config = net.network_xml(
            dir.path(),
            "vas",
            "rover1",
            r#"<access trustClaims="yes">
    <allow kind="call" item="rover1/vas/*" from="ground/*"/>
    <allow kind="file" item="rover1/vas/*" from="ground/*"/>
    <allow kind="publish" item="**" from="ground/*"/>
  </access>"#,
        );
        let mut victim = probe_with_config(
            "victim",
            &config,
            "vas",
            &["--key-file", key.to_str().expect("utf-8 path")],
            &super::victim_cmd(&inbox),
        );
        let ready = victim.expect_key(T, "ready");
        let target = udp(ready["addrs"][0].as_str().expect("the victim's address"));
        let legit = net.keyed("gs", "ground", &key, &super::publishing("position"));
        let mut scene = Scene {
            net,
            dir,
            key,
            inbox,
            victim,
            target,
            legit,
            last: Value::Null,
            strict: true,
        };
        scene.report_until("the legitimate peer's positions", |r| {
            legit_samples(r) >= 5 && r["peers"]["ground/gs"] == 1
        });
        scene
    }

    /// The benchmark's scene (see the module docs).
    pub fn measuring(test: &str) -> Scene {
        let mut scene = Scene::start(test);
        scene.strict = false;
        scene
    }

    /// Waits for a victim report satisfying `pred`: after [`T`] a test fails, a measurement
    /// goes on with the victim's latest report.
    pub fn report_until(&mut self, what: &str, pred: impl Fn(&Value) -> bool) -> Value {
        if self.last.is_object() && pred(&self.last) {
            return self.last.clone();
        }
        let wanted = |v: &Value| v.get("report").is_some_and(&pred);
        let found = if self.strict {
            Some(self.victim.expect(T, what, wanted))
        } else {
            self.victim.try_expect(T, wanted)
        };
        match found {
            Some(v) => self.last = v["report"].clone(),
            None => {
                eprintln!("hostile: no report with {what} within {T:?}: going on with the last");
                if let Some(v) = self
                    .victim
                    .seen
                    .iter()
                    .rev()
                    .find(|v| v.get("report").is_some())
                {
                    self.last = v["report"].clone();
                }
            }
        }
        // `seen` would keep every report of a long run: only the last one matters.
        self.victim.seen.clear();
        self.last.clone()
    }

    /// One attack refused as it must be (`refused`), counted in `tally`: a test fails when it
    /// was not, a measurement counts it as an attack that got through.
    pub fn check(&self, tally: &mut Tally, refused: bool, what: impl std::fmt::Display) {
        assert!(refused || !self.strict, "{what}");
        if !refused {
            eprintln!("hostile: got through: {what}");
        }
        tally.add(1, u64::from(refused));
    }

    /// The legitimate peer's address as the victim knows it.
    pub fn legit_addr(&mut self) -> SocketAddr {
        let r = self.report_until("the legitimate peer's address", |r| {
            r["peer_addrs"]["ground/gs"].is_string()
        });
        udp(r["peer_addrs"]["ground/gs"].as_str().unwrap_or_default())
    }

    /// A legitimate call from ground node `node` (argument 21, answered 42), waiting up to
    /// `wait_ms` for the answer.
    pub fn legit_call(&self, node: &str, wait_ms: u64) -> Proc {
        self.net.keyed(
            node,
            "ground",
            &self.key,
            &[
                "call",
                "--name",
                "rover1/vas/retask",
                "--arg",
                "21",
                "--wait-ms",
                &wait_ms.to_string(),
            ],
        )
    }

    /// The legitimate peer's node id and `replays` of its sealed announcements, read off the
    /// multicast group as any listener on the LAN can.
    pub fn sniff_legit(&mut self, replays: usize) -> (NodeId, Vec<Vec<u8>>) {
        let sniffer = Sniffer::join(self.net.group()).expect("join the multicast group");
        let from = self.legit_addr();
        let mut id = None;
        let mut captured = Vec::new();
        while captured.len() < replays.max(1) {
            let (i, d) = sniffer
                .capture_from(from, T)
                .unwrap_or_else(|| panic!("no announcement of the legitimate peer at {from}"));
            id = Some(i);
            captured.push(d);
        }
        (id.expect("captured at least one"), captured)
    }

    /// What an attacker sent that the victim delivered or executed, one line each: a call
    /// without the legitimate argument, a sample not from the legitimate peer, a file not
    /// from a `ground` node or stored in the sink.
    pub fn got_through(&mut self) -> Vec<String> {
        let r = self.last.clone();
        let mut through = Vec::new();
        let called = r["called"].as_array().cloned().unwrap_or_default();
        through.extend(
            called
                .iter()
                .filter(|c| c.as_u64() != Some(21))
                .map(|c| format!("the victim executed an attacker's call ({c})")),
        );
        let samples = r["samples"].as_object().cloned().unwrap_or_default();
        through.extend(
            samples
                .iter()
                .filter(|(k, _)| *k != LEGIT_SAMPLES)
                .map(|(k, n)| format!("the victim delivered an attacker's samples ({k}: {n})")),
        );
        let files = r["files"].as_array().cloned().unwrap_or_default();
        through.extend(
            files
                .iter()
                .filter(|f| !(f[0] == "fpmo" && f[1] == 7))
                .map(|f| format!("the victim stored an attacker's file ({f})")),
        );
        let stored: Vec<String> = std::fs::read_dir(&self.inbox)
            .map(|rd| {
                rd.filter_map(Result::ok)
                    .map(|e| e.file_name().to_string_lossy().into_owned())
                    .filter(|n| n != ".partial" && n != "legit.xml")
                    .collect()
            })
            .unwrap_or_default();
        through.extend(
            stored
                .iter()
                .map(|n| format!("attacker file {n} in the sink")),
        );
        through
    }

    /// Asserts that nothing an attacker sent was delivered or executed ([`Scene::got_through`]).
    pub fn assert_nothing_from_attackers(&mut self) {
        let through = self.got_through();
        assert!(through.is_empty(), "{through:#?}");
    }

    /// The legitimate traffic still flows: `more` new positions from the legitimate peer, the
    /// peer still known (once), and a call and a file from `ground` nodes served.
    pub fn assert_legit_served(&mut self, more: u64) {
        let before = legit_samples(&self.last);
        let count = |r: &Value, what: &str| r[what].as_array().map_or(0, Vec::len);
        let (calls, files) = (count(&self.last, "called"), count(&self.last, "files"));
        self.report_until("more positions from the legitimate peer", |r| {
            legit_samples(r) >= before + more && r["peers"]["ground/gs"] == 1
        });
        let mut call = self.legit_call("fmo", 10_000);
        let r = outcome(&mut call);
        assert_eq!(r["ok"], 42, "the legitimate call failed: {r}");
        let plan = self.dir.path().join("legit.xml");
        std::fs::write(&plan, b"<plan/>").expect("write the plan");
        let mut send = self.net.keyed(
            "fpmo",
            "ground",
            &self.key,
            &[
                "send",
                "--file",
                plan.to_str().expect("utf-8 path"),
                "--to",
                "rover1/vas/plans",
                "--retry-secs",
                "20",
            ],
        );
        let r = outcome(&mut send);
        assert_eq!(r["done"], 7, "the legitimate file failed: {r}");
        self.report_until("the legitimate call and file", |r| {
            count(r, "called") == calls + 1 && count(r, "files") == files + 1
        });
    }
}

/// A node of an insider's making: a sealed socket of its own that said Hello to `target` as
/// `peer` (node id, node name, namespace), asking for a lease of `lease_ms`.
fn insider_peer(
    key: &DomainKey,
    target: SocketAddr,
    domain: &str,
    (node_id, node, namespace): (NodeId, String, &str),
    lease_ms: u32,
) -> Forger {
    let mut f = Forger::new(Some(key)).expect("a socket");
    f.discovery(
        target,
        &Message::Hello {
            node_id,
            domain: domain.to_owned(),
            node,
            namespace: namespace.to_owned(),
            counter: 0,
            lease_ms,
            gateway: false,
            asks_introduction: false,
        },
    )
    .expect("send");
    f
}

/// A declaration batch from a peer whose log starts at `first`.
fn batch(first: u32, decls: Vec<Declaration>) -> Message {
    let n = decls.len() as u32;
    Message::DeclBatch {
        after: first - 1,
        upto: first - 1 + n,
        reset: false,
        entries: decls
            .into_iter()
            .zip(first..)
            .map(|(decl, counter)| LoggedDeclaration { counter, decl })
            .collect(),
    }
}

fn offer(id: u32, kind: ItemKind, name: &str, ty: TypeInfo, origin: Option<Origin>) -> Declaration {
    Declaration::Offer {
        id,
        service: 1,
        kind,
        name: name.into(),
        ty,
        origin,
    }
}

/// What the victim would run or store if it took an attacker's word: a call of every id a
/// node of a few dozen items may use, a file offer to each, a sample on each.
pub fn forged_session_traffic() -> Vec<Message> {
    let args = encode_payload(&EVIL_ARG).expect("a u64 encodes");
    let position = encode_payload(&[0u8; 32]).expect("bytes encode");
    let mut msgs = Vec::new();
    for id in 1..=24u32 {
        msgs.push(Message::Call {
            call_id: u64::from(id),
            id,
            remaining_ms: 5_000,
            args: args.clone(),
            caller: None,
        });
        msgs.push(Message::FileOffer(FileOffer {
            transfer: u64::from(id),
            sink: id,
            name: "evil.xml".into(),
            size: 7,
            hash: [0; 32],
            sender: None,
        }));
        msgs.push(Message::Var {
            id,
            payload: position.clone(),
        });
    }
    msgs
}

/// The outsider: no key. Every datagram it sends, forged or replayed, must be dropped at the
/// seal (counted as `auth_rejected` or `replay_rejected`).
pub fn outsider(scene: &mut Scene) -> Tally {
    let (legit_id, captured) = scene.sniff_legit(10);
    let at_seal = |r: &Value| refusals(r, "auth_rejected") + refusals(r, "replay_rejected");
    let base = at_seal(&scene.last);
    let target = scene.target;
    let domain = scene.net.domain.clone();
    let mut forger = Forger::new(None).expect("a socket");
    let mut tally = Tally::default();

    // Peers: heartbeats of invented nodes from a thousand source ports, paced on what the
    // victim counted (so the kernel drops none of them).
    let flooded = {
        let mut pace = |n: usize| {
            scene.report_until("the flood counted", |r| at_seal(r) >= base + n as u64);
        };
        attacker::flood_heartbeats(target, &domain, 1000, 100, 0x0bad_0000_0000, &mut pace)
            .expect("flood")
    } as u64;

    // Spoofed names and identity replacement: a Hello as the legitimate peer's name, one
    // with its id, one with an endless lease.
    forger
        .send(target, attacker::hello(0x0bad_0001, &domain, "gs", 60_000))
        .expect("send");
    forger
        .send(target, attacker::hello(legit_id, &domain, "gs", 60_000))
        .expect("send");
    forger
        .send(
            target,
            attacker::hello(0x0bad_0002, &domain, "evil", u32::MAX),
        )
        .expect("send");
    // Bye spoofing.
    for _ in 0..20 {
        forger
            .discovery(target, &Message::Bye { node_id: legit_id })
            .expect("send");
    }
    // A pattern bomb.
    forger
        .send(
            target,
            attacker::interest_batch(7, &format!("{}zz", "**/".repeat(2000))),
        )
        .expect("send");
    // Owned names and origins: the victim's own names, offered for the legitimate peer.
    forger
        .safe(
            target,
            &[batch(
                1,
                vec![
                    Declaration::Service {
                        id: 1,
                        name: "vas".into(),
                    },
                    offer(
                        2,
                        ItemKind::Function,
                        "rover1/vas/retask",
                        TypeInfo::of::<fn(u64) -> u64>(),
                        None,
                    ),
                    offer(
                        3,
                        ItemKind::Variable,
                        "ground/probe/position",
                        TypeInfo::of::<u64>(),
                        Some(Origin {
                            node: legit_id,
                            name: "gs".into(),
                            hops: 0,
                            namespace: "ground".into(),
                        }),
                    ),
                ],
            )],
        )
        .expect("send");
    // Calls, files, samples.
    forger
        .safe(target, &forged_session_traffic())
        .expect("send");
    for m in forged_session_traffic() {
        forger.fast(target, &m).expect("send");
    }
    // Replays of the legitimate peer's sealed announcements, five times each.
    for d in &captured {
        for _ in 0..5 {
            forger.raw(target, d).expect("send");
        }
    }
    let sent = flooded + forger.sent;
    let r = scene.report_until("every datagram of the outsider counted", |r| {
        at_seal(r) >= base + sent
    });
    tally.add(sent, at_seal(&r).saturating_sub(base));
    scene.check(
        &mut tally,
        refusals(&r, "replay_rejected") >= 5 * captured.len() as u64,
        format_args!("replays not counted as such: {r}"),
    );
    tally
}

/// The insider: it has the domain key but the namespace `evil`, which `<access>` allows
/// nothing. Returns the tally of the attacks each refused once by a counter (owned names,
/// origins, forged Byes, second addresses, bad patterns, denied calls and files); the floods
/// (peers, declarations) and the denied publications are checked once each.
pub fn insider(scene: &mut Scene) -> Tally {
    let key = DomainKey::load(&scene.key).expect("the domain key");
    let (legit_id, _) = scene.sniff_legit(1);
    let target = scene.target;
    let domain = scene.net.domain.clone();
    let mut tally = Tally::default();
    let r0 = scene.last.clone();

    // The real API first: a call and a file the `<access>` rules deny.
    let mut call = scene.net.keyed(
        "fmo",
        "evil",
        &scene.key,
        &[
            "call",
            "--name",
            "rover1/vas/retask",
            "--arg",
            &EVIL_ARG.to_string(),
            "--wait-ms",
            "10000",
        ],
    );
    let r = outcome(&mut call);
    let call_denied = r["error"] == "denied";
    scene.check(&mut tally, call_denied, format_args!("the call: {r}"));
    let evil_plan = scene.dir.path().join("evil.xml");
    std::fs::write(&evil_plan, b"<evil/>").expect("write");
    let mut send = scene.net.keyed(
        "fpmo",
        "evil",
        &scene.key,
        &[
            "send",
            "--file",
            evil_plan.to_str().expect("utf-8 path"),
            "--to",
            "rover1/vas/plans",
            "--retry-secs",
            "20",
        ],
    );
    let r = outcome(&mut send);
    let file_denied = r["error"] == "denied";
    scene.check(&mut tally, file_denied, format_args!("the file: {r}"));
    let r1 = scene.report_until("the denied call and file counted", |r| {
        refusals(r, "denied") >= refusals(&r0, "denied") + 2
    });
    tally.add(
        2,
        refusals(&r1, "denied").saturating_sub(refusals(&r0, "denied")),
    );

    // By hand, sealed: a node `evil` of namespace `evil`.
    let mut forger = Forger::new(Some(&key)).expect("a socket");
    let evil_id: NodeId = 0x0e71_0000_0000_0001;
    forger
        .discovery(
            target,
            &Message::Hello {
                node_id: evil_id,
                domain: domain.clone(),
                node: "evil".into(),
                namespace: "evil".into(),
                counter: 5,
                lease_ms: 60_000,
                gateway: false,
                asks_introduction: false,
            },
        )
        .expect("send");
    let r1 = scene.report_until("the insider known as a peer", |r| {
        r["peers"]["evil/evil"] == 1
    });
    // Names it does not own, an origin it may not claim, two bad names.
    forger
        .safe(
            target,
            &[batch(
                1,
                vec![
                    Declaration::Service {
                        id: 1,
                        name: "vas".into(),
                    },
                    offer(
                        2,
                        ItemKind::Variable,
                        "rover1/vas/position",
                        TypeInfo::of::<[u8; 32]>(),
                        None,
                    ),
                    offer(
                        3,
                        ItemKind::Function,
                        "rover1/vas/retask",
                        TypeInfo::of::<fn(u64) -> u64>(),
                        None,
                    ),
                    offer(
                        4,
                        ItemKind::Variable,
                        "evil/x/position",
                        TypeInfo::of::<[u8; 32]>(),
                        Some(Origin {
                            node: legit_id,
                            name: "gs".into(),
                            hops: 0,
                            namespace: "ground".into(),
                        }),
                    ),
                    Declaration::Interest {
                        id: 5,
                        service: 1,
                        kind: ItemKind::Event,
                        pattern: format!("{}zz", "**/".repeat(2000)),
                        ty: TypeInfo::of::<u8>(),
                    },
                ],
            )],
        )
        .expect("send");
    // Bye spoofing and the legitimate peer's id from the insider's address.
    for _ in 0..10 {
        forger
            .discovery(target, &Message::Bye { node_id: legit_id })
            .expect("send");
    }
    for _ in 0..3 {
        forger
            .discovery(
                target,
                &Message::Hello {
                    node_id: legit_id,
                    domain: domain.clone(),
                    node: "gs".into(),
                    namespace: "ground".into(),
                    counter: 1,
                    lease_ms: 60_000,
                    gateway: false,
                    asks_introduction: false,
                },
            )
            .expect("send");
        forger
            .discovery(
                target,
                &Message::Heartbeat {
                    node_id: legit_id,
                    domain_hash: attacker::domain_hash(&domain),
                    counter: 99,
                },
            )
            .expect("send");
    }
    // 3 offers refused, 10 Byes, 6 at a second address; 1 bad pattern.
    let rejected = 3 + 10 + 6;
    let r2 = scene.report_until("the insider's forgeries counted", |r| {
        refusals(r, "rejected") >= refusals(&r1, "rejected") + rejected
            && refusals(r, "bad_declarations") > refusals(&r1, "bad_declarations")
    });
    tally.add(
        rejected,
        refusals(&r2, "rejected").saturating_sub(refusals(&r1, "rejected")),
    );
    tally.add(
        1,
        refusals(&r2, "bad_declarations").saturating_sub(refusals(&r1, "bad_declarations")),
    );
    scene.check(
        &mut tally,
        r2["peers"]["ground/gs"] == 1,
        format_args!("the legitimate peer was evicted or doubled: {r2}"),
    );

    // A declaration flood: past the per-peer cap, refused and counted.
    let flood: Vec<Declaration> = (0..4200u32)
        .map(|i| {
            offer(
                100 + i,
                ItemKind::Variable,
                &format!("evil/flood/item{i}"),
                TypeInfo::of::<u64>(),
                None,
            )
        })
        .collect();
    let mut first = 6;
    for chunk in flood.chunks(600) {
        forger
            .safe(target, &[batch(first, chunk.to_vec())])
            .expect("send");
        first += chunk.len() as u32;
    }
    let capped = |r: &Value| refusals(r, "rejected") >= refusals(&r2, "rejected") + 100;
    let r = scene.report_until("the declaration flood capped", capped);
    scene.check(
        &mut tally,
        capped(&r),
        format_args!("the declaration flood was not capped: {r}"),
    );

    // Samples on the offers it tried, and calls, files and samples on guessed ids.
    for m in forged_session_traffic() {
        forger.fast(target, &m).expect("send");
    }
    forger
        .safe(target, &forged_session_traffic())
        .expect("send");

    // A peer flood: sealed Hellos of 1,100 invented nodes, each from its own port.
    let evicted0 = refusals(&scene.last, "peers_evicted");
    let frames0 = scene.last["frames_in"].as_u64().unwrap_or(0);
    let mut n = 0u64;
    while n < 1100 {
        let mut sockets = Vec::new();
        for _ in 0..100 {
            let peer = (0x0f10_0d00_0000_0000 + n, "flood".to_owned(), "evil");
            sockets.push(insider_peer(&key, target, &domain, peer, u32::MAX));
            n += 1;
        }
        scene.report_until("the peer flood read", |r| {
            r["frames_in"].as_u64().unwrap_or(0) >= frames0 + n
        });
    }
    let pushed_out = |r: &Value| refusals(r, "peers_evicted") > evicted0;
    let r3 = scene.report_until("peers pushed out of the full table", pushed_out);
    scene.check(
        &mut tally,
        pushed_out(&r3) && r3["peers"]["ground/gs"] == 1,
        format_args!("the peer flood took the table, or the legitimate peer: {r3}"),
    );

    // A publisher of its own namespace, which `<access>` does not let publish to us.
    let denied = refusals(&scene.last, "denied");
    let _imp = scene
        .net
        .keyed("imp", "evil", &scene.key, &super::publishing("position"));
    let r = scene.report_until("the impostor's publication denied", |r| {
        refusals(r, "denied") > denied
    });
    scene.check(
        &mut tally,
        refusals(&r, "denied") > denied,
        format_args!("the impostor's publication was not denied: {r}"),
    );
    tally
}

/// Nodes of a declaration churn ([`churn`]): with [`CHURN_INTERESTS`] each, they hold the
/// victim's whole budget of declared items (`MAX_DECLS_TOTAL`, 65,536).
pub const CHURN_PEERS: u64 = 16;
/// Interests each churning node keeps declared (its cap is 4,096 items).
const CHURN_INTERESTS: u32 = 4_000;
/// Declarations per batch while the churners declare their interests.
const CHURN_DECLARE_BATCH: u32 = 500;
/// Declaration changes a second, over all churners: each a 2-entry batch (a withdrawal and a
/// new interest) from the next churner in turn.
const CHURN_BATCHES_PER_S: u64 = 200;

/// How the victim held under a declaration churn ([`churn`]).
#[derive(Debug, Clone, Copy)]
pub struct Churned {
    /// The victim's CPU time while churned, in percent of one core.
    pub victim_cpu_percent: f64,
    /// The same before the churners came.
    pub quiet_cpu_percent: f64,
    /// The legitimate positions delivered a second while churned, against as long before.
    pub legit_rate_ratio: f64,
    /// Whether a fresh legitimate call, made while churned, was answered.
    pub fresh_call_ok: bool,
    /// Declaration batches the churners sent.
    pub batches: u64,
}

/// A node of the churn: a sealed session of its own and its declaration log.
struct Churner {
    forger: Forger,
    /// The counter of its newest declaration.
    counter: u32,
    /// Its live interests' ids, oldest first.
    live: std::collections::VecDeque<u32>,
    next_id: u32,
    n: u64,
}

impl Churner {
    fn interest(&self, id: u32) -> Declaration {
        Declaration::Interest {
            id,
            service: 1,
            kind: ItemKind::Variable,
            // Every one matches every variable the victim publishes: each change concerns
            // all of its routes.
            pattern: "rover1/**".into(),
            ty: TypeInfo::of::<u64>(),
        }
    }

    /// Sends `decls` as the next batch of its log.
    fn declare(&mut self, target: SocketAddr, decls: Vec<Declaration>) {
        let first = self.counter + 1;
        self.counter += decls.len() as u32;
        self.forger
            .safe(target, &[batch(first, decls)])
            .expect("send");
    }

    /// Withdraws its oldest interest and declares a new one, in one batch.
    fn churn(&mut self, target: SocketAddr) {
        let old = self
            .live
            .pop_front()
            .expect("a churner keeps its interests");
        let new = self.next_id;
        self.next_id += 1;
        self.live.push_back(new);
        let decl = self.interest(new);
        self.declare(target, vec![Declaration::Withdraw { id: old }, decl]);
    }
}

/// CPU time process `pid`'s threads have used so far, in seconds (the first field of each
/// `/proc/PID/task/TID/schedstat`, nanoseconds on a core).
fn cpu_seconds(pid: u32) -> f64 {
    let ns: u64 = std::fs::read_dir(format!("/proc/{pid}/task"))
        .map(|tasks| {
            tasks
                .filter_map(Result::ok)
                .filter_map(|t| std::fs::read_to_string(t.path().join("schedstat")).ok())
                .filter_map(|s| s.split_whitespace().next()?.parse::<u64>().ok())
                .sum()
        })
        .unwrap_or(0);
    ns as f64 / 1e9
}

impl Scene {
    /// The victim's newest report: every line it printed so far is read.
    pub fn latest_report(&mut self) -> Value {
        while let Some(v) = self
            .victim
            .try_expect(Duration::ZERO, |v| v.get("report").is_some())
        {
            self.last = v["report"].clone();
        }
        self.victim.seen.clear();
        self.last.clone()
    }

    /// The legitimate positions delivered a second and the victim's CPU percent over `window`.
    fn rates_over(&mut self, window: Duration) -> (f64, f64) {
        let pid = self.victim.pid();
        let (s0, c0, t0) = (
            legit_samples(&self.latest_report()),
            cpu_seconds(pid),
            Instant::now(),
        );
        std::thread::sleep(window);
        let (s1, c1) = (legit_samples(&self.latest_report()), cpu_seconds(pid));
        let secs = t0.elapsed().as_secs_f64();
        (
            s1.saturating_sub(s0) as f64 / secs,
            (c1 - c0) / secs * 100.0,
        )
    }
}

/// An insider's declaration churn: [`CHURN_PEERS`] sealed nodes declare [`CHURN_INTERESTS`]
/// interests each (the victim's whole budget), then change one declaration each in turn,
/// [`CHURN_BATCHES_PER_S`] times a second, while the victim's CPU and the legitimate
/// peer's positions are measured over `window` (and over `window` before the churners
/// came), and a fresh legitimate call is made.
pub fn churn(scene: &mut Scene, window: Duration) -> Churned {
    let key = DomainKey::load(&scene.key).expect("the domain key");
    let target = scene.target;
    let domain = scene.net.domain.clone();
    let (quiet_rate, quiet_cpu) = scene.rates_over(window);
    let declared0 = scene.latest_report()["declarations"].as_u64().unwrap_or(0);

    let mut churners: Vec<Churner> = (0..CHURN_PEERS)
        .map(|n| {
            let peer = (0x0c4e_0000_0000_0000 + n, format!("churn{n}"), "churn");
            let forger = insider_peer(&key, target, &domain, peer, 600_000);
            Churner {
                forger,
                counter: 0,
                live: Default::default(),
                next_id: 2,
                n,
            }
        })
        .collect();
    scene.report_until("the churners known as peers", |r| {
        r["peers"].as_object().is_some_and(|p| {
            p.keys().filter(|k| k.starts_with("churn/")).count() as u64 == CHURN_PEERS
        })
    });
    for c in &mut churners {
        c.declare(
            target,
            vec![Declaration::Service {
                id: 1,
                name: "churn".into(),
            }],
        );
        while c.live.len() < CHURN_INTERESTS as usize {
            let decls: Vec<Declaration> = (0..CHURN_DECLARE_BATCH)
                .map(|_| {
                    let id = c.next_id;
                    c.next_id += 1;
                    c.live.push_back(id);
                    c.interest(id)
                })
                .collect();
            c.declare(target, decls);
        }
    }
    let all = declared0 + CHURN_PEERS * (u64::from(CHURN_INTERESTS) + 1);
    scene.report_until("the churners' interests declared", |r| {
        r["declarations"].as_u64().unwrap_or(0) >= all
    });

    // The churn, on a thread of its own while the victim is measured.
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let churning = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let period = Duration::from_micros(1_000_000 / CHURN_BATCHES_PER_S);
            let start = Instant::now();
            let mut sent = 0u64;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                churners[(sent % CHURN_PEERS) as usize].churn(target);
                sent += 1;
                // Paced to the rate: an attacker's send schedule, not a synchronisation.
                if let Some(wait) =
                    (start + period * sent as u32).checked_duration_since(Instant::now())
                {
                    std::thread::sleep(wait);
                }
            }
            sent
        })
    };
    // Settled into the churn, then measured, with a fresh call in the middle.
    std::thread::sleep(Duration::from_secs(1));
    let mut call = scene.legit_call("fmo", 5_000);
    let calls = scene.latest_report()["called"]
        .as_array()
        .map_or(0, Vec::len);
    let (churned_rate, churned_cpu) = scene.rates_over(window);
    let fresh_call_ok = outcome(&mut call)["ok"] == 42;
    if fresh_call_ok {
        scene.report_until("the fresh call executed", |r| {
            r["called"].as_array().map_or(0, Vec::len) > calls
        });
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let batches = churning.join().expect("the churn thread");
    Churned {
        victim_cpu_percent: churned_cpu,
        quiet_cpu_percent: quiet_cpu,
        legit_rate_ratio: if quiet_rate > 0.0 {
            churned_rate / quiet_rate
        } else {
            0.0
        },
        fresh_call_ok,
        batches,
    }
}

/// Forged peers of a [`confirmed_flood`]: more than the victim's peer table holds (1,024).
const FLOOD_PEERS: u64 = 1_100;
/// Fresh nodes that call the victim after a [`confirmed_flood`].
const FRESH_CALLERS: usize = 3;

/// An insider's flood of peers that look confirmed: [`FLOOD_PEERS`] sealed nodes, each from
/// a socket of its own, say Hello and send one message in a session (an empty declaration
/// batch), but never acknowledge what the victim sends them, as a forged source address cannot.
/// Then [`FRESH_CALLERS`] new nodes of the legitimate namespace call the victim in turn;
/// returns how many of them got their answer, over how many tried. The flood's sockets stay
/// open meanwhile.
pub fn confirmed_flood(scene: &mut Scene) -> f64 {
    let key = DomainKey::load(&scene.key).expect("the domain key");
    let target = scene.target;
    let domain = scene.net.domain.clone();
    let frames0 = scene.latest_report()["frames_in"].as_u64().unwrap_or(0);
    let mut flood = Vec::new();
    for n in 0..FLOOD_PEERS {
        let peer = (0x0c0f_0000_0000_0000 + n, format!("flood{n}"), "evil");
        let mut f = insider_peer(&key, target, &domain, peer, u32::MAX);
        f.safe(target, &[batch(1, Vec::new())]).expect("send");
        flood.push(f);
        // Read as sent (the victim's socket buffer would drop a burst of 2,200).
        if flood.len() % 100 == 0 {
            let sent = 2 * flood.len() as u64;
            scene.report_until("the flood read", |r| {
                r["frames_in"].as_u64().unwrap_or(0) >= frames0 + sent
            });
        }
    }
    let mut answered = 0;
    for k in 0..FRESH_CALLERS {
        let mut call = scene.legit_call(&format!("fresh{k}"), 10_000);
        let r = outcome(&mut call);
        if r["ok"] == 42 {
            answered += 1;
        } else {
            eprintln!("hostile: a fresh caller after the flood of peers: {r}");
        }
    }
    drop(flood);
    answered as f64 / FRESH_CALLERS as f64
}
