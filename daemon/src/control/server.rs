//! The control socket server: a Unix stream socket, one thread per connection, newline-delimited
//! JSON-RPC 2.0 (see [`super::rpc`]).
//!
//! A connection subscribed to the lighting estimate (`lights.subscribe`) gets a second thread that
//! writes its `lights.update` notifications; responses and notifications share one write lock, so
//! lines never interleave. Updates wait in the subscriber's one-slot mailbox (coalesced to the
//! newest, see [`super::lights`]); a subscriber that stops reading for
//! [`ServerOptions::write_timeout`] is disconnected. Neither ever holds up the pipeline or another
//! connection.
//!
//! Access control has two layers: the socket file's mode and group (so that `connect` itself fails
//! for strangers), and the peer's credentials (`SO_PEERCRED`), checked on every connection so
//! that a wrong file mode cannot open the daemon to everyone.

use std::collections::HashMap;
use std::io::{self, Read, Write};
use std::os::unix::fs::{FileTypeExt, MetadataExt, PermissionsExt};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use serde_json::Value;

use super::lights::LightsSubscription;
use super::rpc::{self, Session as _};
use super::types::{ControlError, ControlTarget, codes};

/// Connections served at once; further ones get an error line and are closed.
pub const DEFAULT_MAX_CONNECTIONS: usize = 16;
/// A connection that sends nothing for this long is closed (it would hold a connection slot).
pub const DEFAULT_IDLE_TIMEOUT: Duration = Duration::from_secs(60);
/// A peer that does not read its responses (or notifications) for this long is dropped.
pub const DEFAULT_WRITE_TIMEOUT: Duration = Duration::from_secs(10);
/// Bytes read from the socket at a time.
const READ_CHUNK_BYTES: usize = 8192;

/// Everything [`ControlServer::bind_with`] can tune.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServerOptions {
    /// Permission bits of the socket file.
    pub mode: u32,
    /// Group allowed to connect besides root and the daemon's uid; also the socket file's group.
    pub allowed_gid: Option<u32>,
    /// Longest accepted request line, bytes (without the newline).
    pub max_request_bytes: usize,
    pub max_connections: usize,
    /// A connection that sends nothing for this long is closed, unless it is subscribed.
    pub idle_timeout: Duration,
    /// A peer that does not read what it is sent for this long is disconnected.
    pub write_timeout: Duration,
}

impl Default for ServerOptions {
    fn default() -> Self {
        Self {
            mode: crate::config::DEFAULT_SOCKET_MODE,
            allowed_gid: None,
            max_request_bytes: crate::config::DEFAULT_MAX_REQUEST_BYTES,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            idle_timeout: DEFAULT_IDLE_TIMEOUT,
            write_timeout: DEFAULT_WRITE_TIMEOUT,
        }
    }
}

/// Why the control socket could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error("{}: another process is listening on this socket (is relightd already running?)", path.display())]
    InUse { path: PathBuf },
    #[error("{}: exists and is not a socket; refusing to replace it", path.display())]
    NotASocket { path: PathBuf },
    #[error("{}: {what}: {source}", path.display())]
    Io {
        path: PathBuf,
        what: &'static str,
        source: io::Error,
    },
}

/// The credentials of a connected peer (`SO_PEERCRED`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PeerCred {
    pub pid: Option<u32>,
    pub uid: u32,
    /// The peer's effective gid when it connected.
    pub gid: u32,
}

/// Whether a peer may use the socket: root, the daemon's own user, and members (primary or
/// supplementary) of the configured group.
pub fn peer_allowed(
    cred: &PeerCred,
    daemon_uid: u32,
    allowed_gid: Option<u32>,
    supplementary_groups: &[u32],
) -> bool {
    cred.uid == 0
        || cred.uid == daemon_uid
        || allowed_gid.is_some_and(|gid| cred.gid == gid || supplementary_groups.contains(&gid))
}

/// The supplementary groups listed on the `Groups:` line of a `/proc/<pid>/status` file.
pub fn status_groups(status: &str) -> Vec<u32> {
    status
        .lines()
        .find_map(|line| line.strip_prefix("Groups:"))
        .map(|groups| {
            groups
                .split_whitespace()
                .filter_map(|g| g.parse().ok())
                .collect()
        })
        .unwrap_or_default()
}

/// A bound control socket, not yet accepting; [`ControlServer::spawn`] starts it. Dropping it
/// unspawned removes the socket file.
#[derive(Debug)]
pub struct ControlServer {
    /// `None` once handed to the accept thread.
    listener: Option<UnixListener>,
    shared: Arc<Shared>,
}

/// A running control server. Dropping it shuts it down like [`ControlServerHandle::shutdown`].
#[derive(Debug)]
pub struct ControlServerHandle {
    shared: Arc<Shared>,
    listener: Option<UnixListener>,
    accept_thread: Option<JoinHandle<()>>,
}

struct Shared {
    path: PathBuf,
    /// Device and inode of the socket file we created, so that shutdown removes only ours.
    socket_file: (u64, u64),
    options: ServerOptions,
    target: Arc<dyn ControlTarget>,
    daemon_uid: u32,
    stopping: AtomicBool,
    next_connection: AtomicU64,
    /// Open connections by id.
    connections: Mutex<HashMap<u64, Connection>>,
}

/// An open connection: a clone of its stream (shut down to unblock its thread at shutdown) and
/// the thread serving it.
type Connection = (UnixStream, JoinHandle<()>);

impl std::fmt::Debug for Shared {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Shared")
            .field("path", &self.path)
            .field("options", &self.options)
            .field("daemon_uid", &self.daemon_uid)
            .finish_non_exhaustive()
    }
}

impl ControlServer {
    /// Binds the control socket at `path` with default limits; see [`ControlServer::bind_with`].
    pub fn bind(
        path: impl AsRef<Path>,
        mode: u32,
        allowed_gid: Option<u32>,
        max_request_bytes: usize,
        target: Arc<dyn ControlTarget>,
    ) -> Result<ControlServer, ServerError> {
        let options = ServerOptions {
            mode,
            allowed_gid,
            max_request_bytes,
            ..ServerOptions::default()
        };
        Self::bind_with(path, options, target)
    }

    /// Binds the control socket: replaces a stale socket file (one nobody listens on), sets the
    /// file's mode and, when `allowed_gid` is set, its group.
    pub fn bind_with(
        path: impl AsRef<Path>,
        options: ServerOptions,
        target: Arc<dyn ControlTarget>,
    ) -> Result<ControlServer, ServerError> {
        let path = path.as_ref().to_owned();
        let io_err = |what: &'static str| {
            let path = path.clone();
            move |source| ServerError::Io { path, what, source }
        };
        remove_stale_socket(&path)?;
        let listener = UnixListener::bind(&path).map_err(io_err("cannot bind"))?;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(options.mode))
            .map_err(io_err("cannot set socket mode"))?;
        if let Some(gid) = options.allowed_gid {
            std::os::unix::fs::chown(&path, None, Some(gid))
                .map_err(io_err("cannot set socket group"))?;
        }
        let meta = std::fs::symlink_metadata(&path).map_err(io_err("cannot stat socket"))?;
        tracing::info!(
            path = %path.display(),
            mode = format_args!("{:04o}", options.mode),
            gid = ?options.allowed_gid,
            "control socket listening"
        );
        Ok(ControlServer {
            listener: Some(listener),
            shared: Arc::new(Shared {
                path,
                socket_file: (meta.dev(), meta.ino()),
                options,
                target,
                daemon_uid: rustix::process::getuid().as_raw(),
                stopping: AtomicBool::new(false),
                next_connection: AtomicU64::new(0),
                connections: Mutex::new(HashMap::new()),
            }),
        })
    }

    pub fn path(&self) -> &Path {
        &self.shared.path
    }

    /// Starts the accept thread.
    pub fn spawn(mut self) -> io::Result<ControlServerHandle> {
        let Some(listener) = self.listener.take() else {
            return Err(io::Error::other("control server already spawned"));
        };
        let wake = listener.try_clone()?;
        let shared = Arc::clone(&self.shared);
        let accept_thread = std::thread::Builder::new()
            .name("relightd-control".to_owned())
            .spawn(move || accept_loop(&listener, &shared))?;
        Ok(ControlServerHandle {
            shared: Arc::clone(&self.shared),
            listener: Some(wake),
            accept_thread: Some(accept_thread),
        })
    }
}

impl Drop for ControlServer {
    fn drop(&mut self) {
        if self.listener.take().is_some() {
            remove_own_socket(&self.shared);
        }
    }
}

impl ControlServerHandle {
    pub fn path(&self) -> &Path {
        &self.shared.path
    }

    /// Connections being served now.
    pub fn active_connections(&self) -> usize {
        lock(&self.shared.connections)
            .values()
            .filter(|(_, thread)| !thread.is_finished())
            .count()
    }

    /// Stops accepting, closes every connection, waits for their threads and removes the socket
    /// file (if it is still the one this server created).
    pub fn shutdown(mut self) {
        self.stop();
    }

    fn stop(&mut self) {
        let Some(listener) = self.listener.take() else {
            return;
        };
        self.shared.stopping.store(true, Ordering::SeqCst);
        // On Linux, shutting down a listening socket makes a blocked accept() return EINVAL; the
        // connection attempt is a second wake-up in case it does not.
        let _ = rustix::net::shutdown(&listener, rustix::net::Shutdown::Both);
        let _ = UnixStream::connect(&self.shared.path);
        if let Some(thread) = self.accept_thread.take()
            && thread.join().is_err()
        {
            tracing::error!("control accept thread panicked");
        }
        let connections: Vec<_> = lock(&self.shared.connections).drain().collect();
        for (_, (stream, thread)) in connections {
            let _ = stream.shutdown(std::net::Shutdown::Both);
            if thread.join().is_err() {
                tracing::error!("control connection thread panicked");
            }
        }
        drop(listener);
        remove_own_socket(&self.shared);
        tracing::info!(path = %self.shared.path.display(), "control socket closed");
    }
}

impl Drop for ControlServerHandle {
    fn drop(&mut self) {
        self.stop();
    }
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Removes `path` if it is a socket nobody listens on; refuses to touch anything else.
fn remove_stale_socket(path: &Path) -> Result<(), ServerError> {
    let meta = match std::fs::symlink_metadata(path) {
        Ok(meta) => meta,
        Err(err) if err.kind() == io::ErrorKind::NotFound => return Ok(()),
        Err(source) => {
            return Err(ServerError::Io {
                path: path.to_owned(),
                what: "cannot stat",
                source,
            });
        }
    };
    if !meta.file_type().is_socket() {
        return Err(ServerError::NotASocket {
            path: path.to_owned(),
        });
    }
    match UnixStream::connect(path) {
        Ok(_) => Err(ServerError::InUse {
            path: path.to_owned(),
        }),
        Err(_) => {
            tracing::debug!(path = %path.display(), "removing stale control socket");
            std::fs::remove_file(path).map_err(|source| ServerError::Io {
                path: path.to_owned(),
                what: "cannot remove stale socket",
                source,
            })
        }
    }
}

fn remove_own_socket(shared: &Shared) {
    let ours = std::fs::symlink_metadata(&shared.path)
        .is_ok_and(|meta| (meta.dev(), meta.ino()) == shared.socket_file);
    if ours && let Err(err) = std::fs::remove_file(&shared.path) {
        tracing::warn!(path = %shared.path.display(), %err, "cannot remove control socket");
    }
}

fn accept_loop(listener: &UnixListener, shared: &Arc<Shared>) {
    loop {
        let accepted = listener.accept();
        if shared.stopping.load(Ordering::SeqCst) {
            return;
        }
        match accepted {
            Ok((stream, _)) => admit(stream, shared),
            Err(err) if err.kind() == io::ErrorKind::Interrupted => {}
            Err(err) => {
                // EMFILE and friends: back off instead of spinning; the connection stays queued.
                tracing::warn!(%err, "control socket accept failed");
                std::thread::sleep(Duration::from_millis(100));
            }
        }
    }
}

/// Checks the peer and the connection cap, then starts the connection's thread.
fn admit(mut stream: UnixStream, shared: &Arc<Shared>) {
    let _ = stream.set_write_timeout(Some(shared.options.write_timeout));
    let cred = match rustix::net::sockopt::socket_peercred(&stream) {
        Ok(cred) => PeerCred {
            pid: u32::try_from(cred.pid.as_raw_nonzero().get()).ok(),
            uid: cred.uid.as_raw(),
            gid: cred.gid.as_raw(),
        },
        Err(err) => {
            tracing::warn!(%err, "control connection refused: cannot read peer credentials");
            return;
        }
    };
    let groups = cred
        .pid
        .and_then(|pid| std::fs::read_to_string(format!("/proc/{pid}/status")).ok())
        .map(|status| status_groups(&status))
        .unwrap_or_default();
    if !peer_allowed(
        &cred,
        shared.daemon_uid,
        shared.options.allowed_gid,
        &groups,
    ) {
        tracing::warn!(uid = cred.uid, gid = cred.gid, pid = ?cred.pid, "control connection refused: not allowed");
        refuse(&mut stream, &ControlError::permission_denied(cred.uid));
        return;
    }

    let mut connections = lock(&shared.connections);
    connections.retain(|_, (_, thread)| !thread.is_finished());
    if connections.len() >= shared.options.max_connections {
        drop(connections);
        tracing::warn!(
            uid = cred.uid,
            max = shared.options.max_connections,
            "control connection refused: too many connections"
        );
        let error = ControlError::new(
            codes::TOO_MANY_CONNECTIONS,
            format!(
                "too many connections (at most {})",
                shared.options.max_connections
            ),
        );
        refuse(&mut stream, &error);
        return;
    }
    let Ok(registered) = stream.try_clone() else {
        tracing::warn!("control connection refused: cannot clone the socket");
        return;
    };
    let connection_id = shared.next_connection.fetch_add(1, Ordering::Relaxed);
    tracing::debug!(connection_id, uid = cred.uid, pid = ?cred.pid, "control connection");
    let worker_shared = Arc::clone(shared);
    let spawned = std::thread::Builder::new()
        .name(format!("relightd-ctl-{connection_id}"))
        .spawn(move || {
            serve_connection(stream, &worker_shared, connection_id);
            lock(&worker_shared.connections).remove(&connection_id);
        });
    match spawned {
        Ok(thread) => {
            connections.insert(connection_id, (registered, thread));
        }
        Err(err) => tracing::warn!(%err, "control connection refused: cannot spawn a thread"),
    }
}

fn refuse(stream: &mut UnixStream, error: &ControlError) {
    let mut line = rpc::error_response(Value::Null, error).to_string();
    line.push('\n');
    let _ = stream.write_all(line.as_bytes());
    let _ = stream.shutdown(std::net::Shutdown::Both);
}

fn serve_connection(stream: UnixStream, shared: &Shared, connection_id: u64) {
    if let Err(err) = stream.set_read_timeout(Some(shared.options.idle_timeout)) {
        tracing::warn!(connection_id, %err, "cannot set control read timeout");
    }
    let writer = match stream.try_clone() {
        Ok(writer) => Arc::new(Mutex::new(writer)),
        Err(err) => {
            tracing::warn!(connection_id, %err, "cannot clone control connection");
            return;
        }
    };
    let mut session = ConnectionSession {
        connection_id,
        writer: Arc::clone(&writer),
        lights: LightsPush::Off,
    };
    let max_bytes = shared.options.max_request_bytes;
    let mut reader = LineReader::new(stream, max_bytes);
    loop {
        if shared.stopping.load(Ordering::SeqCst) {
            break;
        }
        let response = match reader.next_line() {
            Ok(ReadLine::Line(line)) => {
                rpc::handle_line_in(&line, shared.target.as_ref(), &mut session)
            }
            Ok(ReadLine::TooLong(bytes)) => {
                tracing::debug!(connection_id, bytes, "control request too large");
                let error = ControlError::invalid_request(format!(
                    "request too large ({bytes} bytes > {max_bytes})"
                ));
                Some(rpc::error_response(Value::Null, &error).to_string())
            }
            Ok(ReadLine::Eof) => break,
            Err(err)
                if matches!(
                    err.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                if session.lights_subscribed() {
                    // Listening for updates is not idling.
                    continue;
                }
                tracing::debug!(connection_id, "control connection idle, closing");
                break;
            }
            Err(err) => {
                tracing::debug!(connection_id, %err, "control connection read failed");
                break;
            }
        };
        if let Some(mut line) = response {
            line.push('\n');
            if let Err(err) = lock(&writer).write_all(line.as_bytes()) {
                tracing::debug!(connection_id, %err, "control connection write failed");
                break;
            }
        }
        session.start_pushing();
    }
    drop(session);
    tracing::debug!(connection_id, "control connection closed");
}

/// A connection's state for the methods that outlive a request.
struct ConnectionSession {
    connection_id: u64,
    /// Shared by responses and notifications, so that lines never interleave.
    writer: Arc<Mutex<UnixStream>>,
    lights: LightsPush,
}

/// The `lights.update` notifications of one connection.
enum LightsPush {
    Off,
    /// Subscribed during the current request; pushing starts once its response is written.
    Armed(LightsSubscription),
    /// A thread writes each update as it comes.
    Running {
        subscription: LightsSubscription,
        thread: JoinHandle<()>,
    },
}

impl ConnectionSession {
    /// Starts the notification thread of a subscription made by the request just answered.
    fn start_pushing(&mut self) {
        let subscription = match std::mem::replace(&mut self.lights, LightsPush::Off) {
            LightsPush::Armed(subscription) => subscription,
            other => {
                self.lights = other;
                return;
            }
        };
        let connection_id = self.connection_id;
        let writer = Arc::clone(&self.writer);
        let pushed = subscription.clone();
        let spawned = std::thread::Builder::new()
            .name(format!("relightd-ctl-{connection_id}-lights"))
            .spawn(move || push_lights(&pushed, &writer, connection_id));
        match spawned {
            Ok(thread) => {
                self.lights = LightsPush::Running {
                    subscription,
                    thread,
                };
            }
            Err(err) => {
                tracing::warn!(
                    connection_id,
                    %err,
                    "lights subscription dropped: cannot spawn a thread"
                );
                subscription.close();
            }
        }
    }
}

impl rpc::Session for ConnectionSession {
    fn lights_subscribed(&self) -> bool {
        match &self.lights {
            LightsPush::Off => false,
            LightsPush::Armed(_) => true,
            LightsPush::Running { thread, .. } => !thread.is_finished(),
        }
    }

    fn subscribe_lights(&mut self, subscription: LightsSubscription) -> Result<(), ControlError> {
        self.unsubscribe_lights();
        tracing::debug!(connection_id = self.connection_id, "lights subscribed");
        self.lights = LightsPush::Armed(subscription);
        Ok(())
    }

    fn unsubscribe_lights(&mut self) {
        match std::mem::replace(&mut self.lights, LightsPush::Off) {
            LightsPush::Off => {}
            LightsPush::Armed(subscription) => subscription.close(),
            LightsPush::Running {
                subscription,
                thread,
            } => {
                subscription.close();
                // At most one write in progress, bounded by the write timeout.
                if thread.join().is_err() {
                    tracing::error!(
                        connection_id = self.connection_id,
                        "lights notification thread panicked"
                    );
                }
            }
        }
    }
}

impl Drop for ConnectionSession {
    fn drop(&mut self) {
        self.unsubscribe_lights();
    }
}

/// Writes a `lights.update` line for each update until the subscription closes. A failed write
/// (the peer went away, or did not read for [`ServerOptions::write_timeout`]) shuts the
/// connection down, which also ends its reading thread.
fn push_lights(subscription: &LightsSubscription, writer: &Mutex<UnixStream>, connection_id: u64) {
    while let Some(estimate) = subscription.recv() {
        let mut line = match rpc::lights_update_line(&*estimate) {
            Ok(line) => line,
            Err(err) => {
                tracing::warn!(connection_id, %err, "cannot encode the lighting estimate");
                continue;
            }
        };
        line.push('\n');
        let writer = lock(writer);
        if let Err(err) = (&*writer).write_all(line.as_bytes()) {
            let coalesced = subscription.coalesced();
            if matches!(
                err.kind(),
                io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
            ) {
                tracing::warn!(
                    connection_id,
                    coalesced,
                    "lights subscriber disconnected: it stopped reading"
                );
            } else {
                tracing::debug!(connection_id, %err, coalesced, "lights subscriber gone");
            }
            let _ = writer.shutdown(std::net::Shutdown::Both);
            subscription.close();
            return;
        }
    }
}

/// One outcome of [`LineReader::next_line`].
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum ReadLine {
    /// A line without its newline (the last line of a stream may lack one).
    Line(Vec<u8>),
    /// A line longer than the cap; it was skipped, not stored. Holds its length in bytes.
    TooLong(usize),
    Eof,
}

/// Splits a byte stream into newline-terminated lines of at most `max_bytes`, skipping longer ones
/// without buffering them.
#[derive(Debug)]
pub(crate) struct LineReader<R> {
    inner: R,
    chunk: Vec<u8>,
    chunk_pos: usize,
    chunk_len: usize,
    line: Vec<u8>,
    max_bytes: usize,
    /// Bytes of the current over-long line seen so far, while skipping it.
    skipped: Option<usize>,
}

impl<R: Read> LineReader<R> {
    pub(crate) fn new(inner: R, max_bytes: usize) -> Self {
        Self {
            inner,
            chunk: vec![0; READ_CHUNK_BYTES],
            chunk_pos: 0,
            chunk_len: 0,
            line: Vec::new(),
            max_bytes,
            skipped: None,
        }
    }

    pub(crate) fn next_line(&mut self) -> io::Result<ReadLine> {
        loop {
            if self.chunk_pos == self.chunk_len {
                let n = match self.inner.read(&mut self.chunk) {
                    Ok(n) => n,
                    Err(err) if err.kind() == io::ErrorKind::Interrupted => continue,
                    Err(err) => return Err(err),
                };
                if n == 0 {
                    if let Some(bytes) = self.skipped.take() {
                        return Ok(ReadLine::TooLong(bytes));
                    }
                    if self.line.is_empty() {
                        return Ok(ReadLine::Eof);
                    }
                    return Ok(ReadLine::Line(std::mem::take(&mut self.line)));
                }
                self.chunk_pos = 0;
                self.chunk_len = n;
            }
            let available = &self.chunk[self.chunk_pos..self.chunk_len];
            let newline = available.iter().position(|&b| b == b'\n');
            let part = &available[..newline.unwrap_or(available.len())];
            self.chunk_pos += part.len() + usize::from(newline.is_some());
            let length = self.skipped.unwrap_or(self.line.len()) + part.len();
            if self.skipped.is_some() || length > self.max_bytes {
                self.line.clear();
                self.skipped = Some(length);
            } else {
                self.line.extend_from_slice(part);
            }
            if newline.is_some() {
                return Ok(match self.skipped.take() {
                    Some(bytes) => ReadLine::TooLong(bytes),
                    None => ReadLine::Line(std::mem::take(&mut self.line)),
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Hands out its bytes in fixed small reads, like a slow peer.
    struct Trickle<'a> {
        data: &'a [u8],
        step: usize,
    }

    impl Read for Trickle<'_> {
        fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
            let n = self.step.min(buf.len()).min(self.data.len());
            let (head, tail) = self.data.split_at(n);
            buf[..n].copy_from_slice(head);
            self.data = tail;
            Ok(n)
        }
    }

    fn lines(data: &[u8], step: usize, max_bytes: usize) -> Vec<ReadLine> {
        let mut reader = LineReader::new(Trickle { data, step }, max_bytes);
        let mut out = Vec::new();
        loop {
            match reader.next_line() {
                Ok(ReadLine::Eof) => return out,
                Ok(line) => out.push(line),
                Err(err) => panic!("in-memory read failed: {err}"),
            }
        }
    }

    #[test]
    fn splits_lines_across_reads() {
        for step in [1, 3, 8192] {
            assert_eq!(
                lines(b"ab\n\ncd\nlast", step, 10),
                vec![
                    ReadLine::Line(b"ab".to_vec()),
                    ReadLine::Line(Vec::new()),
                    ReadLine::Line(b"cd".to_vec()),
                    ReadLine::Line(b"last".to_vec()),
                ]
            );
        }
    }

    #[test]
    fn skips_long_lines_and_counts_them() {
        let mut data = vec![b'x'; 30_000];
        data.extend_from_slice(b"\nok\n");
        data.extend_from_slice(&[b'y'; 11]);
        for step in [1, 7, 8192] {
            assert_eq!(
                lines(&data, step, 10),
                vec![
                    ReadLine::TooLong(30_000),
                    ReadLine::Line(b"ok".to_vec()),
                    ReadLine::TooLong(11),
                ]
            );
        }
    }

    #[test]
    fn line_of_exactly_the_cap_is_accepted() {
        assert_eq!(
            lines(b"0123456789\n01234567890\n", 4, 10),
            vec![
                ReadLine::Line(b"0123456789".to_vec()),
                ReadLine::TooLong(11)
            ]
        );
    }

    #[test]
    fn proc_status_groups() {
        let status =
            "Name:\tbash\nUid:\t1000\t1000\t1000\t1000\nGroups:\t4 24 27 1000 \nNgid:\t0\n";
        assert_eq!(status_groups(status), vec![4, 24, 27, 1000]);
        assert_eq!(status_groups("Groups:\n"), Vec::<u32>::new());
        assert_eq!(status_groups("Name: x\n"), Vec::<u32>::new());
    }

    #[test]
    fn peer_decision() {
        let peer = |uid, gid| PeerCred {
            pid: Some(42),
            uid,
            gid,
        };
        let daemon_uid = 990;
        // root and the daemon's own user always
        assert!(peer_allowed(&peer(0, 0), daemon_uid, None, &[]));
        assert!(peer_allowed(&peer(990, 990), daemon_uid, None, &[]));
        // anyone else only through the configured group
        assert!(!peer_allowed(&peer(1000, 1000), daemon_uid, None, &[]));
        assert!(!peer_allowed(&peer(1000, 1000), daemon_uid, Some(44), &[]));
        assert!(!peer_allowed(
            &peer(1000, 1000),
            daemon_uid,
            Some(44),
            &[27, 46]
        ));
        assert!(peer_allowed(&peer(1000, 44), daemon_uid, Some(44), &[]));
        assert!(peer_allowed(
            &peer(1000, 1000),
            daemon_uid,
            Some(44),
            &[27, 44]
        ));
        // a supplementary group does not help without a configured group
        assert!(!peer_allowed(&peer(1000, 1000), daemon_uid, None, &[44]));
    }
}
