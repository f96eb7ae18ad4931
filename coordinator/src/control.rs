//! `WorkerControl`: one bidirectional stream per worker. The first message registers the
//! worker; the stream's end (or silence past the timeout) means the worker is gone.

use std::pin::Pin;
use std::sync::Arc;

use rayfarm_node::proto::worker_control_server::WorkerControl;
use rayfarm_node::proto::{self, worker_message::Body};
use tokio::sync::mpsc;
use tokio_stream::wrappers::UnboundedReceiverStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};
use tracing::warn;

use crate::state::Coordinator;
use rayfarm_node::fault::Faults;

/// The worker control service.
pub struct Control {
    coordinator: Arc<Coordinator>,
    faults: Faults,
}

impl Control {
    pub fn new(coordinator: Arc<Coordinator>, faults: Faults) -> Self {
        Control {
            coordinator,
            faults,
        }
    }
}

type OutStream = Pin<Box<dyn Stream<Item = Result<proto::CoordinatorMessage, Status>> + Send>>;

#[tonic::async_trait]
impl WorkerControl for Control {
    type AttachStream = OutStream;

    async fn attach(
        &self,
        request: Request<Streaming<proto::WorkerMessage>>,
    ) -> Result<Response<OutStream>, Status> {
        // Under mutual TLS: the names of the worker's certificate, which its id and address
        // must match.
        let certified = rayfarm_node::identity::of_request(&request);
        let mut inbound = request.into_inner();
        let first = inbound
            .message()
            .await?
            .ok_or_else(|| Status::invalid_argument("the stream ended before registering"))?;
        let Some(Body::Register(register)) = first.body else {
            return Err(Status::invalid_argument(
                "the first message must be a Register",
            ));
        };
        let (tx, rx) = mpsc::unbounded_channel();
        let key = self
            .coordinator
            .register(&register, certified.as_deref(), tx)?;
        let coordinator = self.coordinator.clone();
        tokio::spawn(async move {
            let why = loop {
                match inbound.message().await {
                    Ok(Some(msg)) => match msg.body {
                        Some(body) => coordinator.worker_message(key, body),
                        None => warn!(key, "empty message from a worker"),
                    },
                    Ok(None) => break "stream closed".to_string(),
                    Err(status) => break format!("stream failed: {}", status.message()),
                }
            };
            coordinator.worker_gone(key, &why);
        });
        let rx = self.faults.delayed(&register.worker_id, rx);
        // The copy of a shared message (the last holder takes it as it is) is made here, in
        // this worker's response stream, not under the state's lock where it was queued.
        let out = UnboundedReceiverStream::new(rx).map(|m| m.map(Arc::unwrap_or_clone));
        Ok(Response::new(Box::pin(out)))
    }
}
