//! The coordinator's side of the world: what reaches it, the commits the checks follow, and
//! what it answers, leaving once it is done planning.

use crate::coord::ToNode;
use crate::net::{COORDINATOR, NodeId};

use super::{Msg, World};

impl World<'_> {
    pub(super) fn at_coordinator(&mut self, from: NodeId, msg: Msg) {
        let now = self.now;
        let out = match msg {
            Msg::Register(r, conn) => self.coord.register(now, from, conn, r),
            Msg::ToCoordinator(body, conn) => self.coord.message(now, from, conn, body),
            Msg::StreamEnded(conn) => self.coord.gone(now, from, conn),
            _ => Vec::new(),
        };
        for &(frame, tile, at) in &self.coord.commits[self.checks.commits_seen..] {
            self.checks.commit(frame, tile, at);
        }
        self.checks.commits_seen = self.coord.commits.len();
        self.carry_out(out);
    }

    /// Sends what the coordinator answered, once it is done planning (it handles one thing
    /// at a time, so what it sends leaves when all it was given so far is done).
    pub(super) fn carry_out(&mut self, out: Vec<ToNode>) {
        let depart = self.coord.free_at;
        for o in out {
            match o {
                ToNode::Send(node, conn, m) => {
                    self.send_at(depart, COORDINATOR, node, Msg::Control(m, conn))
                }
                ToNode::Close(node, conn) => {
                    self.send_at(depart, COORDINATOR, node, Msg::Closed(conn))
                }
            }
        }
    }
}
