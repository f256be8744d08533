//! A blocking client of the control socket, used by `relightctl` and by end-to-end tests.

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

/// One connection to the control socket; requests are answered in order.
#[derive(Debug)]
pub struct Client {
    writer: UnixStream,
    reader: BufReader<UnixStream>,
    timeout: Duration,
    next_id: u64,
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
        let response = self.read_response()?;
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

    /// Writes bytes as they are (the caller adds the newline).
    pub fn send_raw(&mut self, bytes: &[u8]) -> Result<(), ClientError> {
        self.writer
            .write_all(bytes)
            .and_then(|()| self.writer.flush())
            .map_err(|err| self.io_error(err))
    }

    /// Reads one response line and parses it as JSON.
    pub fn read_response(&mut self) -> Result<Value, ClientError> {
        let mut line = Vec::new();
        let read = (&mut self.reader)
            .take(MAX_RESPONSE_BYTES)
            .read_until(b'\n', &mut line)
            .map_err(|err| self.io_error(err))?;
        if read == 0 {
            return Err(ClientError::Closed);
        }
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
