//! The gRPC services of `proto/rayfarm/v1` (the user API, the worker control stream, the peer
//! bundle stream) over the message types of `rayfarm-proto`, which this module re-exports.

#![allow(missing_docs, clippy::all, clippy::pedantic)]

pub use rayfarm_proto::*;

tonic::include_proto!("rayfarm.v1");

#[cfg(test)]
mod tests {
    use prost::Message;

    use super::*;

    #[test]
    fn control_messages_round_trip_through_protobuf() {
        let msg = CoordinatorMessage {
            body: Some(coordinator_message::Body::RoundPlan(RoundPlan {
                job_id: "j1".into(),
                round: 7,
                work_on: vec![3, 5],
                evict: vec![1],
                holders: vec![DomainHolders {
                    domain: 3,
                    workers: vec![2],
                    lost: vec![5],
                }],
                next: vec![4],
                holders_delta: true,
                sole_holders: Vec::new(),
                report_hold_ms: 50,
            })),
        };
        let bytes = msg.encode_to_vec();
        assert_eq!(CoordinatorMessage::decode(bytes.as_slice()).unwrap(), msg);
        assert!(CoordinatorMessage::decode(&b"\xff\xff\xff"[..]).is_err());
        assert_eq!(Schedule::try_from(3), Ok(Schedule::Dynamic));
    }
}
