//! A blocking client of the control socket, used by `relightctl` and by end-to-end tests.
//!
//! Notifications the daemon sends (`lights.update` after `lights.subscribe`) may arrive while a
//! call waits for its response; they are kept, in order, for [`Client::next_notification`].

use std::collections::VecDeque;
use std::io::{self, BufRead, BufReader, Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde_json::{Value, json};

use super::types::ControlError;

/// Longest response line the client accepts, bytes (a status report is a few KiB).
const MAX_RESPONSE_BYTES: u64 = 64 * 1024 * 1024;

/// Why a call did not return a result.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("cannot connect to {}: {source} (is relightd running? try `systemctl status relightd`)", path.display())]
    Connect { path: PathBuf, source: io::Error },
    #[error("no response within {0:?}")]
    Timeout(Duration),
    #[error("the daemon closed the connection")]
    Closed,
    #[error("control socket I/O: {0}")]
    Io(#[source] io::Error),
    #[error("malformed response: {0}")]
    Protocol(String),
    /// The daemon answered with a JSON-RPC error.
    #[error("{}", .0.message)]
    Rpc(ControlError),
}

/// A notification from the daemon: a JSON-RPC request without `id`.
#[derive(Debug, Clone, PartialEq)]
pub struct Notification {
    pub method: String,
    /// `null` when the notification has no params.
    pub params: Value,
}

impl Notification {
    /// The notification `message` holds, if it is one (a `method` and no `id`).
    pub fn from_message(message: &Value) -> Option<Notification> {
        let object = message.as_object()?;
        if object.contains_key("id") {
            return None;
        }
        Some(Notification {
            method: object.get("method")?.as_str()?.to_owned(),
            params: object.get("params").cloned().unwrap_or(Value::Null),
        })
    }
}

/// Notifications kept while calls wait for their responses, at most; older ones are dropped.
const MAX_QUEUED_NOTIFICATIONS: usize = 1024;

/// One connection to the control socket; requests are answered in order.
#[derive(Debug)]
pub struct Client {
    writer: UnixStream,
    reader: BufReader<UnixStream>,
    timeout: Duration,
    next_id: u64,
    /// Notifications read while waiting for a response.
    notifications: VecDeque<Notification>,
    /// The start of a line whose end has not arrived yet (a read timed out in between).
    partial: Vec<u8>,
}

impl Client {
    /// Connects to the socket at `path`; `timeout` bounds every later read and write.
    pub fn connect(path: impl AsRef<Path>, timeout: Duration) -> Result<Client, ClientError> {
        let path = path.as_ref();
        let connect_err = |source| ClientError::Connect {
            path: path.to_owned(),
            source,
        };
        let stream = UnixStream::connect(path).map_err(connect_err)?;
        let timeout = timeout.max(Duration::from_millis(1));
        stream
            .set_read_timeout(Some(timeout))
            .and_then(|()| stream.set_write_timeout(Some(timeout)))
            .map_err(ClientError::Io)?;
        let reader = BufReader::new(stream.try_clone().map_err(ClientError::Io)?);
        Ok(Client {
            writer: stream,
            reader,
            timeout,
            next_id: 1,
            notifications: VecDeque::new(),
            partial: Vec::new(),
        })
    }

    /// Calls `method` and returns its result; a JSON-RPC error becomes [`ClientError::Rpc`].
    pub fn call(&mut self, method: &str, params: Option<Value>) -> Result<Value, ClientError> {
        let id = self.next_id;
        self.next_id += 1;
        let mut request = json!({ "jsonrpc": "2.0", "method": method, "id": id });
        if let Some(params) = params {
            request["params"] = params;
        }
        let mut line = request.to_string();
        line.push('\n');
        if let Err(err) = self.send_raw(line.as_bytes()) {
            // A refused connection (permission, too many clients) has an error line waiting.
            return match self.read_response() {
                Ok(response) => Err(response_error(&response).unwrap_or(err)),
                Err(_) => Err(err),
            };
        }
        let response = loop {
            let message = self.read_response()?;
            match Notification::from_message(&message) {
                Some(notification) => self.queue_notification(notification),
                None => break message,
            }
        };
        if let Some(err) = response_error(&response) {
            return Err(err);
        }
        if response.get("id") != Some(&Value::from(id)) {
            return Err(ClientError::Protocol(format!(
                "response id {} does not match request id {id}",
                response.get("id").unwrap_or(&Value::Null)
            )));
        }
        response
            .get("result")
            .cloned()
            .ok_or_else(|| ClientError::Protocol("response has neither result nor error".into()))
    }

    /// Sends a notification (no `id`, no response).
    pub fn notify(&mut self, method: &str, params: Option<Value>) -> Result<(), ClientError> {
        let mut request = json!({ "jsonrpc": "2.0", "method": method });
        if let Some(params) = params {
            request["params"] = params;
        }
        let mut line = request.to_string();
        line.push('\n');
        self.send_raw(line.as_bytes())
    }

    /// The next notification from the daemon: one that arrived during a call, else the next
    /// line read (waiting at most the timeout; [`ClientError::Timeout`] leaves the connection
    /// usable). A line that is not a notification is a protocol error.
    pub fn next_notification(&mut self) -> Result<Notification, ClientError> {
        if let Some(notification) = self.notifications.pop_front() {
            return Ok(notification);
        }
        let message = self.read_response()?;
        Notification::from_message(&message)
            .ok_or_else(|| ClientError::Protocol(format!("expected a notification, got {message}")))
    }

    fn queue_notification(&mut self, notification: Notification) {
        if self.notifications.len() == MAX_QUEUED_NOTIFICATIONS {
            self.notifications.pop_front();
        }
        self.notifications.push_back(notification);
    }

    /// Writes bytes as they are (the caller adds the newline).
    pub fn send_raw(&mut self, bytes: &[u8]) -> Result<(), ClientError> {
        self.writer
            .write_all(bytes)
            .and_then(|()| self.writer.flush())
            .map_err(|err| self.io_error(err))
    }

    /// Reads one line (a response or a notification) and parses it as JSON.
    ///
    /// A timeout in the middle of a line keeps what was read, so the next read goes on from
    /// there.
    pub fn read_response(&mut self) -> Result<Value, ClientError> {
        let limit = MAX_RESPONSE_BYTES.saturating_sub(self.partial.len() as u64);
        let read = (&mut self.reader)
            .take(limit)
            .read_until(b'\n', &mut self.partial);
        let read = read.map_err(|err| self.io_error(err))?;
        if read == 0 && self.partial.is_empty() {
            return Err(ClientError::Closed);
        }
        let line = std::mem::take(&mut self.partial);
        if line.last() != Some(&b'\n') {
            return Err(ClientError::Protocol(format!(
                "response line not terminated after {} bytes",
                line.len()
            )));
        }
        serde_json::from_slice(&line).map_err(|err| ClientError::Protocol(err.to_string()))
    }

    fn io_error(&self, err: io::Error) -> ClientError {
        match err.kind() {
            io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut => {
                ClientError::Timeout(self.timeout)
            }
            _ => ClientError::Io(err),
        }
    }
}

/// The error object of a response, if it has one.
fn response_error(response: &Value) -> Option<ClientError> {
    let error = response.get("error")?;
    Some(
        match serde_json::from_value::<ControlError>(error.clone()) {
            Ok(error) => ClientError::Rpc(error),
            Err(err) => ClientError::Protocol(format!("malformed error object {error}: {err}")),
        },
    )
}
