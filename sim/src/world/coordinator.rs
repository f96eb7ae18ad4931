//! The coordinator's side of the world: what reaches it, the commits the checks follow, and
//! what it answers, leaving once it is done planning. What reaches it while it plans waits,
//! and is taken all at once when it is done, so the reports among it make one round.

use crate::coord::{Arrival, ToNode};
use crate::net::{COORDINATOR, NodeId};

use super::{Ev, Msg, World};

impl World<'_> {
    pub(super) fn at_coordinator(&mut self, from: NodeId, msg: Msg) {
        let now = self.now;
        if self.coord.is_busy(now) {
            // It is planning: this waits, and is taken with whatever else arrives meanwhile.
            let arrival = match msg {
                Msg::Register(r, conn) => Arrival::Register(from, conn, r),
                Msg::ToCoordinator(body, conn) => Arrival::Message(from, conn, body),
                Msg::StreamEnded(conn) => Arrival::Gone(from, conn),
                _ => return,
            };
            if let Some(at) = self.coord.wait(arrival) {
                self.heap.push(at, Ev::CoordFree);
            }
            return;
        }
        let out = match msg {
            Msg::Register(r, conn) => self.coord.register(now, from, conn, r),
            Msg::ToCoordinator(body, conn) => self.coord.message(now, from, conn, body),
            Msg::StreamEnded(conn) => self.coord.gone(now, from, conn),
            _ => Vec::new(),
        };
        self.note_commits();
        self.carry_out(out);
    }

    /// The coordinator is done planning: it takes what waited (`SimCoordinator::take_waiting`).
    pub(super) fn coordinator_free(&mut self) {
        match self.coord.take_waiting(self.now) {
            Ok(out) => {
                self.note_commits();
                self.carry_out(out);
            }
            Err(later) => self.heap.push(later, Ev::CoordFree),
        }
    }

    /// The coordinator's periodic work, waiting like a message if it is busy.
    pub(super) fn coordinator_tick(&mut self) {
        if self.coord.is_busy(self.now) {
            if let Some(at) = self.coord.wait(Arrival::Tick) {
                self.heap.push(at, Ev::CoordFree);
            }
            return;
        }
        let out = self.coord.tick(self.now);
        self.carry_out(out);
    }

    /// Hands the commits the coordinator made since the last look to the checks.
    fn note_commits(&mut self) {
        for &(frame, tile, at) in &self.coord.commits[self.checks.commits_seen..] {
            self.checks.commit(frame, tile, at);
        }
        self.checks.commits_seen = self.coord.commits.len();
    }

    /// Sends what the coordinator answered, once it is done planning (it handles one thing
    /// at a time, so what it sends leaves when all it was given so far is done).
    pub(super) fn carry_out(&mut self, out: Vec<ToNode>) {
        let depart = self.coord.free_at;
        for o in out {
            match o {
                ToNode::Send(node, conn, m) => {
                    self.send_at(depart, COORDINATOR, node, Msg::Control(*m, conn))
                }
                ToNode::Close(node, conn) => {
                    self.send_at(depart, COORDINATOR, node, Msg::Closed(conn))
                }
            }
        }
    }
}
