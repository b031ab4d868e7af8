//! Mission XML, structure-aware: generated mission files (nodes with namespaces, the services
//! `usal run` knows with mostly sensible attributes, a radio, a station naming a plan that
//! exists) with a share of bent values and XML damage, through [`Mission::parse`]. Checks:
//! never a panic; a mission that parses has unique node names and at most one station.

use std::fmt::Write;
use std::path::{Path, PathBuf};

use arbitrary::{Result, Unstructured};

use super::{Mission, ServiceSpec};

/// The repository's `config/missions`, where the generated stations' plans exist: from the root
/// package (`cargo test`) or from `fuzz` (cargo-fuzz).
fn missions_dir() -> PathBuf {
    let here = Path::new(env!("CARGO_MANIFEST_DIR"));
    let root = if here.ends_with("fuzz") {
        here.join("..")
    } else {
        here.to_path_buf()
    };
    root.join("config/missions")
}

fn value(u: &mut Unstructured<'_>, good: &[&'static str], bent: bool) -> Result<String> {
    if bent && u.ratio(1u8, 4)? {
        Ok((*u.choose(&[
            "",
            "NaN",
            "inf",
            "-1",
            "1e30",
            "1e308",
            "-1e308",
            "0",
            "x",
            "18446744073709551616",
            "a b",
            "&amp;",
            "0.5e",
            "4294967296",
        ])?)
        .to_owned())
    } else {
        Ok((*u.choose(good)?).to_owned())
    }
}

/// A mission document.
fn mission(u: &mut Unstructured<'_>) -> Result<String> {
    let bent = u.ratio(1u8, 3)?;
    let mut s = String::from("<?xml version=\"1.0\"?>\n<mission");
    let _ = write!(
        s,
        " name=\"{}\"",
        value(u, &["m", "rover-demo", "x_1"], bent)?
    );
    if u.arbitrary()? {
        let _ = write!(
            s,
            " timeoutS=\"{}\"",
            value(u, &["300", "0.5", "60"], bent)?
        );
    }
    if u.arbitrary()? {
        let _ = write!(s, " domain=\"{}\"", value(u, &["d1", "fleet"], bent)?);
    }
    s.push_str(">\n");
    let nodes = u.int_in_range(1usize..=4)?;
    let names = ["air", "ground", "relay", "air2"];
    let mut stations = 0;
    for i in 0..nodes {
        let name = if bent && u.ratio(1u8, 6)? {
            names[0]
        } else {
            names[i]
        };
        let _ = write!(s, "  <node name=\"{name}\"");
        if u.arbitrary()? {
            let _ = write!(
                s,
                " namespace=\"{}\"",
                value(u, &["rover1", "gcs", "r2"], bent)?
            );
        }
        s.push_str(">\n");
        for _ in 0..u.int_in_range(0u8..=4)? {
            match u.int_in_range(0u8..=6)? {
                0 => {
                    let _ = writeln!(
                        s,
                        "    <mavsim vehicle=\"{}\" home=\"{}\" speedup=\"{}\"/>",
                        value(u, &["rover", "copter", "plane"], bent)?,
                        value(u, &["41.27500,1.98700,0", "0,0,0"], bent)?,
                        value(u, &["5", "1", "20"], bent)?
                    );
                }
                1 => {
                    let _ = writeln!(
                        s,
                        "    <vas vehicle=\"{}\" queueSize=\"{}\" telemetryHz=\"{}\"/>",
                        value(u, &["rover", "copter", "plane"], bent)?,
                        value(u, &["5", "1", "50"], bent)?,
                        value(u, &["4", "10", "0.5"], bent)?
                    );
                }
                2 => {
                    let _ = writeln!(
                        s,
                        "    <fpma vehicle=\"{}\" lookahead=\"{}\"/>",
                        value(u, &["rover", "aircraft"], bent)?,
                        value(u, &["8", "1", "100"], bent)?
                    );
                }
                3 => s.push_str("    <fmo/>\n"),
                4 => s.push_str("    <fpmo listen=\"127.0.0.1:0\"/>\n"),
                5 if stations == 0 || bent => {
                    stations += 1;
                    let _ = writeln!(
                        s,
                        "    <station plan=\"{}\"/>",
                        value(
                            u,
                            &[
                                "../flightplans/rover-demo.xml",
                                "../flightplans/rover-carpark.xml"
                            ],
                            bent
                        )?
                    );
                }
                _ => {}
            }
        }
        s.push_str("  </node>\n");
    }
    if nodes >= 2 && u.ratio(1u8, 3)? {
        let _ = writeln!(
            s,
            "  <radio ground=\"{}\" air=\"{}\" baud=\"{}\" loss=\"{}\" corrupt=\"{}\"/>",
            names[1],
            names[0],
            value(u, &["57600", "9600"], bent)?,
            value(u, &["0", "0.05"], bent)?,
            value(u, &["0", "0.01"], bent)?
        );
    }
    s.push_str("</mission>\n");
    if bent && u.ratio(1u8, 3)? {
        let mut b = s.into_bytes();
        let i = u.int_in_range(0..=b.len() - 1)?;
        let j = u.int_in_range(i..=b.len().min(i + 40))?;
        if u.arbitrary()? {
            b.drain(i..j);
        } else {
            let piece = b[i..j].to_vec();
            b.splice(j..j, piece);
        }
        s = String::from_utf8_lossy(&b).into_owned();
    }
    Ok(s)
}

/// One fuzz case: a mission generated from `data`, parsed; never a panic, and a mission that
/// parses has unique node names and at most one station.
pub fn check(data: &[u8]) {
    let Ok(doc) = mission(&mut Unstructured::new(data)) else {
        return;
    };
    if let Ok(m) = Mission::parse(&doc, &missions_dir()) {
        for (i, n) in m.nodes.iter().enumerate() {
            assert!(
                m.nodes[..i].iter().all(|o| o.name != n.name),
                "duplicate node {} accepted:\n{doc}",
                n.name
            );
        }
        let stations = m
            .nodes
            .iter()
            .flat_map(|n| &n.services)
            .filter(|s| matches!(s, ServiceSpec::Station(_)))
            .count();
        assert!(stations <= 1, "{stations} stations accepted:\n{doc}");
    }
}

/// Found by this test: `timeoutS="1e30"` made `Duration::from_secs_f64` panic.
#[test]
fn a_huge_timeout_is_an_error_not_a_panic() {
    let base = missions_dir();
    for t in ["1e30", "1e308"] {
        let doc = format!(
            "<mission name=\"m\" timeoutS=\"{t}\"><node name=\"air\"><fmo/></node></mission>"
        );
        let err = Mission::parse(&doc, &base).expect_err("a timeout past Duration's range");
        assert!(err.message.contains("timeoutS"), "{}", err.message);
    }
}

#[test]
fn structured_fuzz_mission_xml() {
    use rand::{Rng, SeedableRng};
    use std::time::{Duration, Instant};
    // A cap on the wall-clock time only shortens the run in slow debug builds.
    let started = Instant::now();
    let mut parsed = 0;
    for seed in 0..400u64 {
        if started.elapsed() > Duration::from_secs(4) {
            break;
        }
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed ^ 0x3155);
        let mut data = vec![0u8; rng.random_range(0..1024usize)];
        rng.fill(&mut data[..]);
        if let Ok(doc) = mission(&mut Unstructured::new(&data)) {
            parsed += usize::from(Mission::parse(&doc, &missions_dir()).is_ok());
        }
        if let Err(e) = std::panic::catch_unwind(|| check(&data)) {
            panic!("seed {seed} failed: {e:?}");
        }
    }
    assert!(parsed > 0, "no generated mission parsed");
}
