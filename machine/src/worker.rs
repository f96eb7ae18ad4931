//! The worker machine: a frame's queues, routing, the bundler, speculation groups, reports.
