//! The Zenoh link: the node's datagrams carried by an Eclipse Zenoh session, so that nodes of one
//! domain that share no LAN (no multicast, not even a route to each other) meet through Zenoh
//! routers over TCP or TLS.
//!
//! Zenoh is only the medium here, as UDP is for the Ethernet link: the sessions, the ARQ, the
//! batching and the seal are the [`DatagramLink`]'s, so every guarantee of marea holds across a
//! router as across a LAN, including across a router restart (Zenoh drops what was in flight
//! there; the ARQ resends it, and nothing is delivered twice).
//!
//! Keys (the `@` chunks are Zenoh's verbatim chunks: no `*` or `**` of another client matches
//! them, so a tool subscribing to `usal/D/**` never sees marea's datagrams):
//! ```text
//! usal/<domain>/@marea/hello        discovery datagrams (Hello, Heartbeat, Bye) to every link
//! usal/<domain>/@marea/<id:016x>    datagrams to the link whose random id is <id>
//! usal/<domain>/@node/<node>        liveliness token, held while the node lives
//! payload := from:u64le datagram    the sending link's id, then the datagram as on UDP
//! ```

use std::io;
use std::sync::Arc;

use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use zenoh::qos::CongestionControl;
use zenoh::Wait;

use super::arq::{ArqConfig, RetryLimit};
use super::auth::LinkSecurity;
use super::datagram::link::{DatagramLink, DatagramLinkOptions, Medium};
use super::{LinkHandler, PeerAddr, ZenohMode};

/// The Zenoh link: a [`DatagramLink`] over a Zenoh session.
pub type ZenohLink = DatagramLink<ZenohMedium>;

/// How the Zenoh link is set up (taken from `<zenoh>` in network.xml and the node).
#[derive(Debug, Clone)]
pub struct ZenohLinkOptions {
    /// Link name.
    pub name: String,
    /// How the session joins.
    pub mode: ZenohMode,
    /// Endpoints to connect to.
    pub connect: Vec<String>,
    /// Endpoints to listen on.
    pub listen: Vec<String>,
    /// A Zenoh configuration file under the attributes.
    pub config_file: Option<std::path::PathBuf>,
    /// The link's lease: retransmission keeps a session this long without an acknowledgement
    /// (an outage up to the lease loses nothing).
    pub lease: std::time::Duration,
    /// The discovery domain: the links of one domain meet under `usal/<domain>`.
    pub domain: String,
    /// The node's name, for its liveliness token.
    pub node: String,
    /// ARQ tuning.
    pub arq: ArqConfig,
    /// The domain key: when set, every datagram is sealed and only sealed ones are taken.
    pub security: Option<LinkSecurity>,
}

/// Why the Zenoh link could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum ZenohLinkOpenError {
    /// The Zenoh configuration file could not be read or is not valid.
    #[error("link {link}: Zenoh configuration {path}: {reason}")]
    ConfigFile {
        /// Link name.
        link: String,
        /// The file.
        path: String,
        /// What Zenoh said.
        reason: String,
    },
    /// An attribute could not be applied to the Zenoh configuration (an endpoint Zenoh does not
    /// accept).
    #[error("link {link}: Zenoh refused {key} = {value}: {reason}")]
    Config {
        /// Link name.
        link: String,
        /// The configuration key.
        key: &'static str,
        /// The value.
        value: String,
        /// What Zenoh said.
        reason: String,
    },
    /// The session could not be opened (no router reachable in client mode, a listening
    /// endpoint taken).
    #[error(
        "link {link}: cannot open the Zenoh session ({mode} mode, connect {connect}): {reason}"
    )]
    Session {
        /// Link name.
        link: String,
        /// `client` or `peer`.
        mode: &'static str,
        /// The endpoints it connects to.
        connect: String,
        /// What Zenoh said.
        reason: String,
    },
}

/// What [`serialize_zenoh_io`] sets `ZENOH_RUNTIME` to: every Zenoh runtime handed over to its
/// application runtime, of one worker thread.
pub const ZENOH_RUNTIME_ONE_THREAD: &str = "(rx: (handover: app), tx: (handover: app), acc: (handover: app), net: (handover: app), app: (worker_threads: 1))";

/// Whether a Zenoh configuration connects or listens over TLS.
pub fn uses_tls(config: &zenoh::Config) -> bool {
    ["connect/endpoints", "listen/endpoints"]
        .iter()
        .any(|key| config.get_json(key).is_ok_and(|v| v.contains("tls/")))
}

/// Has Zenoh run its network I/O on one thread (`ZENOH_RUNTIME` =
/// [`ZENOH_RUNTIME_ONE_THREAD`]), unless the environment already says how it should run.
///
/// Zenoh 1.10's TLS link reads and writes one TLS connection from two tasks at once, through
/// an `UnsafeCell` (eclipse-zenoh/zenoh#2557): on two threads they corrupt the connection's
/// state, and a router under load died of SIGSEGV inside rustls (3 routers of 6 runs of
/// `launcher::the_rover_wan_failsafe_mission_completes_across_a_router_restart_and_an_outage`
/// under two CPU hogs; none of 9 on one thread). On one thread the two tasks take turns. Zenoh
/// reads the variable when a process opens its first session: a later call changes nothing.
/// Returns whether it set the variable.
pub fn serialize_zenoh_io() -> bool {
    static SET: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *SET.get_or_init(|| {
        if std::env::var_os("ZENOH_RUNTIME").is_some() {
            return false;
        }
        std::env::set_var("ZENOH_RUNTIME", ZENOH_RUNTIME_ONE_THREAD);
        tracing::debug!(
            "Zenoh's network I/O on one thread (its TLS link is unsound on two: zenoh#2557)"
        );
        true
    })
}

/// Largest datagram the link builds: Zenoh fragments it on the wire, and a datagram is what the
/// ARQ resends whole after a loss (only a router restart or an outage loses one).
const DATAGRAM_MAX: usize = 32 * 1024;

/// Datagrams received and not yet taken by the receive task; beyond it Zenoh's thread drops
/// them (the ARQ resends what was safe), so a stalled node cannot make Zenoh's threads wait.
const RECEIVE_QUEUE: usize = 4096;

/// A datagram as Zenoh's thread hands it to the receive task.
struct Received {
    from: u64,
    /// Arrived on the discovery key.
    announce: bool,
    /// The datagram, without the sender id.
    datagram: Vec<u8>,
}

/// Zenoh as a [`Medium`]: a session, this link's key and the domain's discovery key.
pub struct ZenohMedium {
    session: zenoh::Session,
    /// This link's id: its key is `<prefix>/<me:016x>`.
    me: u64,
    /// `usal/<domain>/@marea`.
    prefix: String,
    /// `<prefix>/hello`.
    hello: String,
    /// The liveliness token `usal/<domain>/@node/<node>`, held for the session's life.
    _alive: zenoh::liveliness::LivelinessToken,
}

impl ZenohMedium {
    fn put(&self, key: &str, d: &[u8]) -> io::Result<()> {
        let mut payload = Vec::with_capacity(8 + d.len());
        payload.extend_from_slice(&self.me.to_le_bytes());
        payload.extend_from_slice(d);
        // Never wait for a congested router: the ARQ resends what was safe.
        self.session
            .put(key, payload)
            .congestion_control(CongestionControl::Drop)
            .wait()
            .map_err(|e| io::Error::other(e.to_string()))
    }

    /// The Zenoh session's id (as `zenoh://<zid>` in the link's address).
    pub fn zid(&self) -> String {
        self.session.zid().to_string()
    }
}

impl Medium for ZenohMedium {
    type Addr = u64;

    fn peer_addr(addr: u64) -> PeerAddr {
        PeerAddr::Zenoh(addr)
    }

    fn medium_addr(to: PeerAddr) -> Option<u64> {
        match to {
            PeerAddr::Zenoh(id) => Some(id),
            _ => None,
        }
    }

    fn send_to(&self, d: &[u8], to: u64) -> io::Result<()> {
        self.put(&format!("{}/{to:016x}", self.prefix), d)
    }

    fn announce_targets(&self) -> usize {
        1
    }

    fn announce_to(&self, d: &[u8], _target: usize) -> io::Result<()> {
        self.put(&self.hello, d)
    }

    fn datagram_max(&self, _to: u64) -> usize {
        DATAGRAM_MAX
    }

    fn local_addr(&self) -> String {
        format!("zenoh://{}/{:016x}", self.zid(), self.me)
    }
}

/// How long a client's session waits at start for a router to answer, without a `config` file.
pub const CLIENT_CONNECT_WAIT_MS: u64 = 15_000;

/// The Zenoh configuration of a link: its `config` file if any, with `mode`, `connect` and
/// `listen` applied over it. Without a file, multicast scouting is off (a router, or the
/// endpoints given, is how a node meets the others) and a client waits up to
/// [`CLIENT_CONNECT_WAIT_MS`] for its router at start (then the node fails to open, naming it).
///
/// # Errors
/// [`ZenohLinkOpenError::ConfigFile`] or [`ZenohLinkOpenError::Config`].
pub fn zenoh_config(c: &ZenohLinkOptions) -> Result<zenoh::Config, ZenohLinkOpenError> {
    let mut config = match &c.config_file {
        Some(path) => {
            zenoh::Config::from_file(path).map_err(|e| ZenohLinkOpenError::ConfigFile {
                link: c.name.clone(),
                path: path.display().to_string(),
                reason: e.to_string(),
            })?
        }
        None => zenoh::Config::default(),
    };
    let mut set = |key: &'static str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|e| ZenohLinkOpenError::Config {
                link: c.name.clone(),
                key,
                value,
                reason: e.to_string(),
            })
    };
    // Endpoints hold no whitespace (the parser refuses it); Debug quotes and escapes as JSON.
    let json_list = |v: &[String]| {
        let quoted: Vec<String> = v.iter().map(|e| format!("{e:?}")).collect();
        format!("[{}]", quoted.join(","))
    };
    set("mode", format!("\"{}\"", c.mode.as_str()))?;
    if !c.connect.is_empty() {
        set("connect/endpoints", json_list(&c.connect))?;
    }
    if !c.listen.is_empty() {
        set("listen/endpoints", json_list(&c.listen))?;
    }
    if c.config_file.is_none() {
        set("scouting/multicast/enabled", "false".into())?;
        if c.mode == ZenohMode::Client {
            // A node started with its router (a mission, a vehicle booting) waits for it a
            // while instead of failing at once; once connected, Zenoh reconnects by itself.
            set("connect/timeout_ms", CLIENT_CONNECT_WAIT_MS.to_string())?;
        }
    }
    Ok(config)
}

impl DatagramLink<ZenohMedium> {
    /// Opens the Zenoh session, declares the link's subscribers and liveliness token, and
    /// starts the receive and transmit tasks on `tasks`, stopping on `cancel` (which also
    /// closes the session).
    ///
    /// # Errors
    /// [`ZenohLinkOpenError`] when the configuration is refused or the session cannot open.
    pub async fn open(
        index: usize,
        options: ZenohLinkOptions,
        handler: Arc<dyn LinkHandler>,
        tasks: &TaskTracker,
        cancel: CancellationToken,
    ) -> Result<Arc<Self>, ZenohLinkOpenError> {
        let c = &options;
        let config = zenoh_config(c)?;
        let session_err = |e: zenoh::Error| ZenohLinkOpenError::Session {
            link: c.name.clone(),
            mode: c.mode.as_str(),
            connect: if c.connect.is_empty() {
                "(none)".into()
            } else {
                c.connect.join(",")
            },
            reason: e.to_string(),
        };
        if uses_tls(&config) {
            serialize_zenoh_io();
        }
        let session = zenoh::open(config).await.map_err(session_err)?;
        let me: u64 = rand::random();
        let prefix = format!("usal/{}/@marea", options.domain);
        let hello = format!("{prefix}/hello");
        let (tx, rx) = mpsc::channel::<Received>(RECEIVE_QUEUE);
        let mut subscribers = Vec::new();
        for (key, announce) in [
            (format!("{prefix}/{me:016x}"), false),
            (hello.clone(), true),
        ] {
            let tx = tx.clone();
            let sub = session
                .declare_subscriber(key)
                .callback(move |sample| {
                    let payload = sample.payload().to_bytes();
                    let Some((from, datagram)) = payload.split_first_chunk::<8>() else {
                        return;
                    };
                    let from = u64::from_le_bytes(*from);
                    if from == me {
                        return;
                    }
                    let _ = tx.try_send(Received {
                        from,
                        announce,
                        datagram: datagram.to_vec(),
                    });
                })
                .await
                .map_err(session_err)?;
            subscribers.push(sub);
        }
        let alive = session
            .liveliness()
            .declare_token(format!("usal/{}/@node/{}", options.domain, options.node))
            .await
            .map_err(session_err)?;
        let medium = ZenohMedium {
            session: session.clone(),
            me,
            prefix,
            hello,
            _alive: alive,
        };
        let link = DatagramLink::create(
            index,
            DatagramLinkOptions {
                name: c.name.clone(),
                arq: options.arq,
                retry_limit: RetryLimit {
                    after: options.lease.max(RetryLimit::lan().after),
                    ..RetryLimit::lan()
                },
                security: options.security,
            },
            medium,
            handler,
            tasks,
            cancel.clone(),
        );
        let l = link.clone();
        crate::sync::spawn_tracked(tasks, async move {
            receive_loop(l, rx, cancel).await;
            drop(subscribers);
            if let Err(e) = session.close().await {
                tracing::debug!(error = %e, "Zenoh session did not close cleanly");
            }
        });
        Ok(link)
    }
}

async fn receive_loop(
    link: Arc<ZenohLink>,
    mut rx: mpsc::Receiver<Received>,
    cancel: CancellationToken,
) {
    loop {
        let first = tokio::select! {
            _ = cancel.cancelled() => break,
            r = rx.recv() => match r {
                Some(r) => r,
                None => break,
            },
        };
        let mut touched = Vec::new();
        let mut take = |mut r: Received| {
            if r.announce {
                link.receive_announce(&mut r.datagram, r.from);
            } else {
                link.receive(&mut r.datagram, r.from, &mut touched);
            }
        };
        take(first);
        // What else is waiting, so that acknowledgements are batched (as the UDP link does).
        for _ in 0..64 {
            match rx.try_recv() {
                Ok(r) => take(r),
                Err(_) => break,
            }
        }
        link.received(touched);
    }
}
