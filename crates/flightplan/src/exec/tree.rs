//! Finding nodes in a plan: the node list a frame stack points into, a node by id, and the frame
//! stack that leads to a node.

use super::cursor::{Frame, FrameKind};
use crate::model::*;

pub(super) fn child_list<'a>(node: &'a Node, kind: &FrameKind) -> Option<&'a [Node]> {
    match (&node.kind, kind) {
        (NodeKind::Iterative(it), FrameKind::Loop { .. }) => Some(&it.body),
        (NodeKind::Alternative(a), FrameKind::Branch(b)) => {
            a.branches.get(*b).map(|br| br.body.as_slice())
        }
        _ => None,
    }
}

/// The node list the innermost frame indexes.
pub(super) fn list_of<'a>(plan: &'a FlightPlan, frames: &[Frame]) -> &'a [Node] {
    let Some(FrameKind::Stage(s)) = frames.first().map(|f| &f.kind) else {
        return &[];
    };
    let mut list: &[Node] = plan.stage(*s);
    for w in frames.windows(2) {
        list = match list.get(w[0].index).and_then(|n| child_list(n, &w[1].kind)) {
            Some(l) => l,
            None => return &[],
        };
    }
    list
}

/// The node list the innermost frame indexes, mutable; `None` if the cursor does not match the
/// plan (it always does: the cursor is built over this plan and only leaves are replaced).
pub(super) fn list_mut<'a>(
    plan: &'a mut FlightPlan,
    frames: &[Frame],
) -> Option<&'a mut Vec<Node>> {
    let Some(FrameKind::Stage(stage)) = frames.first().map(|f| &f.kind) else {
        return None;
    };
    let mut list = plan.stage_mut(*stage);
    for w in frames.windows(2) {
        let node = list.get_mut(w[0].index)?;
        list = match (&mut node.kind, &w[1].kind) {
            (NodeKind::Iterative(it), FrameKind::Loop { .. }) => &mut it.body,
            (NodeKind::Alternative(a), FrameKind::Branch(b)) => &mut a.branches.get_mut(*b)?.body,
            _ => return None,
        };
    }
    Some(list)
}

pub(super) fn node_mut<'a>(plan: &'a mut FlightPlan, id: &str) -> Option<&'a mut Node> {
    pub(super) fn walk<'a>(nodes: &'a mut [Node], id: &str) -> Option<&'a mut Node> {
        for n in nodes.iter_mut() {
            if n.id == id {
                return Some(n);
            }
            let found = match &mut n.kind {
                NodeKind::Iterative(it) => walk(&mut it.body, id),
                NodeKind::Alternative(a) => {
                    a.branches.iter_mut().find_map(|b| walk(&mut b.body, id))
                }
                _ => None,
            };
            if found.is_some() {
                return found;
            }
        }
        None
    }
    let FlightPlan {
        takeoff,
        departure,
        mission,
        approach,
        landing,
        ..
    } = plan;
    [takeoff, departure, mission, approach, landing]
        .into_iter()
        .find_map(|l| walk(l, id))
}

/// The cursor that points at node `id`.
pub(super) fn path_to(plan: &FlightPlan, id: &str) -> Option<Vec<Frame>> {
    pub(super) fn search(list: &[Node], id: &str, frames: &mut Vec<Frame>) -> bool {
        for (i, n) in list.iter().enumerate() {
            if let Some(f) = frames.last_mut() {
                f.index = i;
            }
            if n.id == id {
                return true;
            }
            match &n.kind {
                NodeKind::Iterative(it) => {
                    frames.push(Frame {
                        index: 0,
                        kind: FrameKind::Loop {
                            iteration: 0,
                            produced: false,
                            waits: false,
                        },
                    });
                    if search(&it.body, id, frames) {
                        return true;
                    }
                    frames.pop();
                }
                NodeKind::Alternative(a) => {
                    for (b, br) in a.branches.iter().enumerate() {
                        frames.push(Frame {
                            index: 0,
                            kind: FrameKind::Branch(b),
                        });
                        if search(&br.body, id, frames) {
                            return true;
                        }
                        frames.pop();
                    }
                }
                _ => {}
            }
        }
        false
    }
    for s in Stage::ALL {
        let mut frames = vec![Frame {
            index: 0,
            kind: FrameKind::Stage(s),
        }];
        if search(plan.stage(s), id, &mut frames) {
            return Some(frames);
        }
    }
    None
}
