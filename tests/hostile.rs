//! Hostile tests, all real processes: a victim node (`marea-probe victim`, keyed, `<access>`
//! rules allowing only `ground/*`), a legitimate peer publishing positions to it, and an
//! attacker trying every attack of the suite: an outsider without the key, then an insider with
//! the key but another namespace. Nothing from the attacker is delivered or executed (the
//! victim's report of what it ran, delivered and stored), the legitimate traffic keeps flowing
//! (counts), and the victim's counters show every rejection. The attacks are in
//! `tests/common/hostile.rs`, shared with the `hostile.rejected_ratio` benchmark.

mod common;

use common::hostile::{self, legit_samples, refusals, Scene};

#[test]
fn an_outsider_without_the_key_gets_nothing_through_and_every_datagram_is_counted() {
    let mut scene = Scene::start("hostile-outsider");
    let before = legit_samples(&scene.last);
    let tally = hostile::outsider(&mut scene);
    assert_eq!(tally.ratio(), 1.0, "{tally:?}");
    assert!(tally.sent > 1000, "{tally:?}");
    let r = scene.last.clone();
    assert!(
        legit_samples(&r) > before,
        "no legitimate positions during the attack: {r}"
    );
    // Nothing unauthenticated reached discovery: the only peer is the legitimate one.
    let peers = r["peers"].as_object().cloned().unwrap_or_default();
    assert_eq!(peers.len(), 1, "{peers:?}");
    assert_eq!(refusals(&r, "rejected"), 0, "refused past the seal: {r}");
    scene.assert_nothing_from_attackers();
    scene.assert_legit_served(25);
    scene.assert_nothing_from_attackers();
}

#[test]
fn an_insider_of_another_namespace_gets_nothing_through_and_every_refusal_is_counted() {
    let mut scene = Scene::start("hostile-insider");
    let before = legit_samples(&scene.last);
    let tally = hostile::insider(&mut scene);
    assert_eq!(tally.ratio(), 1.0, "{tally:?}");
    let r = scene.last.clone();
    assert!(
        legit_samples(&r) > before,
        "no legitimate positions during the attack: {r}"
    );
    assert_eq!(r["peers"]["ground/gs"], 1, "{r}");
    scene.assert_nothing_from_attackers();
    scene.assert_legit_served(25);
    scene.assert_nothing_from_attackers();
}

#[test]
fn an_insider_churning_declarations_at_the_caps_leaves_calls_answered_and_positions_flowing() {
    let mut scene = Scene::start("hostile-churn");
    let churned = hostile::churn(&mut scene, std::time::Duration::from_secs(3));
    assert!(churned.fresh_call_ok, "{churned:?}");
    assert!(churned.batches > 100, "{churned:?}");
    let r = scene.latest_report();
    assert_eq!(r["peers"]["ground/gs"], 1, "{r}");
    scene.assert_legit_served(25);
    scene.assert_nothing_from_attackers();
}

#[test]
fn an_insiders_peers_that_never_answer_leave_room_for_new_nodes() {
    let mut scene = Scene::start("hostile-confirmed-flood");
    let answered = hostile::confirmed_flood(&mut scene);
    assert_eq!(answered, 1.0, "fresh callers answered after the flood");
    let r = scene.latest_report();
    assert_eq!(r["peers"]["ground/gs"], 1, "{r}");
    assert!(refusals(&r, "peers_evicted") > 0, "{r}");
    scene.assert_nothing_from_attackers();
}

/// Insiders with identities of their own running as the victim's name: the FPMa's key as
/// node `vas` of `rover1` (a node name the roster does not list it for) and the station's as
/// namespace `rover1`. Every fresh caller reaches the genuine victim; no squatter runs a call.
#[test]
fn squatters_of_a_proven_name_answer_no_caller() {
    let a = common::trust::squat("hostile-squat");
    assert_eq!(a.hijacked, 0, "{a:?}");
    assert_eq!(a.genuine, common::trust::CALLERS, "{a:?}");
    assert_eq!(a.answered, common::trust::CALLERS, "{a:?}");
}

/// An insider's gateway (a key the roster lists for any namespace, not as a gateway) forwards
/// a provider of the victim's names from a LAN of its own to the callers' LAN, beside the
/// domain's gateway to the victim: none of its forwarded offers is taken, every fresh caller
/// reaches the genuine victim.
#[test]
fn a_self_declared_gateway_answers_no_caller() {
    let a = common::trust::gateway_forgery("hostile-gateway-forgery");
    assert_eq!(a.hijacked, 0, "{a:?}");
    assert_eq!(a.genuine, common::trust::CALLERS, "{a:?}");
    assert_eq!(a.answered, common::trust::CALLERS, "{a:?}");
}

/// Item 1 of "Trust that holds inside the domain": an insider with the domain key forges a
/// proven station's source address (calls, file offers, marked samples), replays the
/// station's frames it read off the LAN, reflects the victim's own frames back to it, and
/// says `Bye` as the station from its address.
/// Where both ends proved their identities, every frame between them is sealed with their
/// pair's keys: nothing forged runs or is delivered, every replayed and reflected frame is
/// refused at the seal, and the station's positions keep flowing.
#[test]
fn frames_forged_replayed_or_reflected_as_a_proven_station_are_refused() {
    let Some(f) = common::trust::forged_as_station("hostile-forged-station") else {
        return test_support::tool_missing(
            "raw sockets (root or CAP_NET_RAW), which forging a source address takes",
            "run the tests as root, or give the test binary CAP_NET_RAW",
        );
    };
    assert_eq!(f.calls_executed, 0, "{f:?}");
    assert_eq!(f.samples_delivered, 0, "{f:?}");
    assert!(
        f.replayed >= 12 && f.reflected >= 2,
        "too little captured to replay and reflect: {f:?}"
    );
    assert_eq!(f.replays_accepted, 0, "{f:?}");
    assert_eq!(f.forged_refused, f.forged, "{f:?}");
    assert!(f.legit_flowing, "{f:?}");
}
