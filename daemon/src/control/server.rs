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
//!
//! Fairness ([`admission`]): no client can lock the others out. A request line must be complete
//! within [`ServerOptions::request_deadline`] of its first byte (a peer trickling one byte at a
//! time is cut off, whatever its pace); one uid holds at most
//! [`ServerOptions::max_connections_per_uid`] request connections; subscribers are counted
//! apart from request connections, under [`ServerOptions::max_subscribers`]; the last
//! connection slot is kept for root and the daemon's own user, so `status` and `rpc.ping`
//! always get through to them; and a batch's reply is capped at
//! [`ServerOptions::max_reply_bytes`].

use std::collections::HashMap;
use std::io::{self, Read, Write};
use std::os::unix::fs::{FileTypeExt, MetadataExt, PermissionsExt};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serde_json::Value;

use super::lights::LightsSubscription;
use super::rpc::{self, Session as _};
use super::types::{ControlError, ControlTarget, codes};
use crate::lock;

/// Connections served at once; further ones get an error line and are closed.
pub const DEFAULT_MAX_CONNECTIONS: usize = 16;
/// A connection that sends nothing for this long is closed (it would hold a connection slot).
pub const DEFAULT_IDLE_TIMEOUT: Duration = Duration::from_secs(60);
/// A peer that does not read its responses (or notifications) for this long is dropped.
pub const DEFAULT_WRITE_TIMEOUT: Duration = Duration::from_secs(10);
/// A request line must be complete this long after its first byte.
pub const DEFAULT_REQUEST_DEADLINE: Duration = Duration::from_secs(10);
/// Request connections one uid (other than root and the daemon's) may hold at once.
pub const DEFAULT_MAX_CONNECTIONS_PER_UID: usize = 4;
/// Connections subscribed to the lighting estimate at once.
pub const DEFAULT_MAX_SUBSCRIBERS: usize = 8;
/// Largest reply to one batch, bytes.
pub const DEFAULT_MAX_REPLY_BYTES: usize = 1 << 20;
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
    /// A request line not complete this long after its first byte closes the connection.
    pub request_deadline: Duration,
    /// Request connections one uid may hold (root and the daemon's own user are exempt).
    pub max_connections_per_uid: usize,
    /// Connections subscribed to `lights.update`, counted apart from `max_connections`.
    pub max_subscribers: usize,
    /// A batch whose reply would be larger gets an error naming the limit instead.
    pub max_reply_bytes: usize,
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
            request_deadline: DEFAULT_REQUEST_DEADLINE,
            max_connections_per_uid: DEFAULT_MAX_CONNECTIONS_PER_UID,
            max_subscribers: DEFAULT_MAX_SUBSCRIBERS,
            max_reply_bytes: DEFAULT_MAX_REPLY_BYTES,
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

/// Whether a peer is root or the daemon's own user: exempt from the per-uid cap, and the only
/// ones who may take the last connection slot.
fn privileged(uid: u32, daemon_uid: u32) -> bool {
    uid == 0 || uid == daemon_uid
}

/// Whether a new request connection may be served, given the request connections open now
/// (`open`, subscribers not counted) and how many of them its uid holds (`open_by_uid`); the
/// refusal says which limit it hit.
pub fn admission(
    options: &ServerOptions,
    privileged: bool,
    open: usize,
    open_by_uid: usize,
) -> Result<(), String> {
    let max = options.max_connections;
    if open >= max {
        return Err(format!("too many connections (at most {max})"));
    }
    if privileged {
        return Ok(());
    }
    if open + 1 >= max {
        return Err(format!(
            "too many connections (at most {max}; the last is kept for root and the daemon's user)"
        ));
    }
    if open_by_uid >= options.max_connections_per_uid {
        return Err(format!(
            "too many connections from this user (at most {})",
            options.max_connections_per_uid
        ));
    }
    Ok(())
}

/// The peer's supplementary groups: the process's own from `/proc/<pid>/status`, or, where
/// `/proc` hides other users' processes (systemd's `ProtectProc=invisible`), its user's from
/// the group database (`getgrouplist`).
fn peer_groups(cred: &PeerCred) -> Vec<u32> {
    if let Some(status) = cred
        .pid
        .and_then(|pid| std::fs::read_to_string(format!("/proc/{pid}/status")).ok())
    {
        return status_groups(&status);
    }
    user_groups(cred.uid, cred.gid)
}

/// The groups the user database gives `uid` (with `gid` as its primary group); empty when the
/// user has no entry.
pub fn user_groups(uid: u32, gid: u32) -> Vec<u32> {
    use nix::unistd::{Gid, Uid, User, getgrouplist};
    let Ok(Some(user)) = User::from_uid(Uid::from_raw(uid)) else {
        return Vec::new();
    };
    let Ok(name) = std::ffi::CString::new(user.name) else {
        return Vec::new();
    };
    getgrouplist(&name, Gid::from_raw(gid))
        .map(|groups| groups.into_iter().map(Gid::as_raw).collect())
        .unwrap_or_default()
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
    /// Connections subscribed to the lighting estimate now.
    subscribers: AtomicUsize,
}

/// An open connection: a clone of its stream (shut down to unblock its thread at shutdown), the
/// thread serving it, its peer's uid, and whether it is subscribed (then it does not count as a
/// request connection).
struct Connection {
    stream: UnixStream,
    thread: JoinHandle<()>,
    uid: u32,
    subscribed: Arc<AtomicBool>,
}

impl Connection {
    fn is_request(&self) -> bool {
        !self.thread.is_finished() && !self.subscribed.load(Ordering::Acquire)
    }
}

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
                subscribers: AtomicUsize::new(0),
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
            .filter(|c| !c.thread.is_finished())
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
        for (_, connection) in connections {
            let _ = connection.stream.shutdown(std::net::Shutdown::Both);
            if connection.thread.join().is_err() {
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
    let groups = peer_groups(&cred);
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
    connections.retain(|_, c| !c.thread.is_finished());
    let open = connections.values().filter(|c| c.is_request()).count();
    let open_by_uid = connections
        .values()
        .filter(|c| c.is_request() && c.uid == cred.uid)
        .count();
    if let Err(reason) = admission(
        &shared.options,
        privileged(cred.uid, shared.daemon_uid),
        open,
        open_by_uid,
    ) {
        drop(connections);
        tracing::warn!(uid = cred.uid, open, "control connection refused: {reason}");
        refuse(
            &mut stream,
            &ControlError::new(codes::TOO_MANY_CONNECTIONS, reason),
        );
        return;
    }
    let Ok(registered) = stream.try_clone() else {
        tracing::warn!("control connection refused: cannot clone the socket");
        return;
    };
    let connection_id = shared.next_connection.fetch_add(1, Ordering::Relaxed);
    tracing::debug!(connection_id, uid = cred.uid, pid = ?cred.pid, "control connection");
    let worker_shared = Arc::clone(shared);
    let subscribed = Arc::new(AtomicBool::new(false));
    let worker_subscribed = Arc::clone(&subscribed);
    let spawned = std::thread::Builder::new()
        .name(format!("relightd-ctl-{connection_id}"))
        .spawn(move || {
            serve_connection(stream, &worker_shared, connection_id, worker_subscribed);
            lock(&worker_shared.connections).remove(&connection_id);
        });
    match spawned {
        Ok(thread) => {
            connections.insert(
                connection_id,
                Connection {
                    stream: registered,
                    thread,
                    uid: cred.uid,
                    subscribed,
                },
            );
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

fn serve_connection(
    stream: UnixStream,
    shared: &Shared,
    connection_id: u64,
    subscribed: Arc<AtomicBool>,
) {
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
        subscribed,
        subscribers: &shared.subscribers,
        max_subscribers: shared.options.max_subscribers,
    };
    let max_bytes = shared.options.max_request_bytes;
    let mut reader = LineReader::new(stream, max_bytes)
        .with_timeouts(shared.options.idle_timeout, shared.options.request_deadline);
    loop {
        if shared.stopping.load(Ordering::SeqCst) {
            break;
        }
        let response = match reader.next_line() {
            Ok(ReadLine::Line(line)) => rpc::handle_line_capped(
                &line,
                shared.target.as_ref(),
                &mut session,
                shared.options.max_reply_bytes,
            ),
            Ok(ReadLine::TooLong(bytes)) => {
                tracing::debug!(connection_id, bytes, "control request too large");
                let error = ControlError::invalid_request(format!(
                    "request too large ({bytes} bytes > {max_bytes})"
                ));
                Some(rpc::error_response(Value::Null, &error).to_string())
            }
            Ok(ReadLine::Eof) => break,
            Ok(ReadLine::Overdue(bytes)) => {
                tracing::debug!(connection_id, bytes, "control request not finished in time");
                let error = ControlError::invalid_request(format!(
                    "request line not finished within {} s of its first byte ({bytes} bytes received); closing",
                    shared.options.request_deadline.as_secs_f64()
                ));
                let mut line = rpc::error_response(Value::Null, &error).to_string();
                line.push('\n');
                let _ = lock(&writer).write_all(line.as_bytes());
                break;
            }
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
struct ConnectionSession<'a> {
    connection_id: u64,
    /// Shared by responses and notifications, so that lines never interleave.
    writer: Arc<Mutex<UnixStream>>,
    lights: LightsPush,
    /// Seen by admission: a subscribed connection is not a request connection.
    subscribed: Arc<AtomicBool>,
    /// Subscribed connections of the whole server, and their cap.
    subscribers: &'a AtomicUsize,
    max_subscribers: usize,
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

impl ConnectionSession<'_> {
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

impl rpc::Session for ConnectionSession<'_> {
    fn lights_subscribed(&self) -> bool {
        match &self.lights {
            LightsPush::Off => false,
            LightsPush::Armed(_) => true,
            LightsPush::Running { thread, .. } => !thread.is_finished(),
        }
    }

    fn subscribe_lights(&mut self, subscription: LightsSubscription) -> Result<(), ControlError> {
        self.unsubscribe_lights();
        let max = self.max_subscribers;
        if self
            .subscribers
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n < max).then_some(n + 1)
            })
            .is_err()
        {
            subscription.close();
            return Err(ControlError::busy(format!(
                "too many lights subscribers (at most {max})"
            )));
        }
        self.subscribed.store(true, Ordering::Release);
        tracing::debug!(connection_id = self.connection_id, "lights subscribed");
        self.lights = LightsPush::Armed(subscription);
        Ok(())
    }

    fn unsubscribe_lights(&mut self) {
        if !matches!(self.lights, LightsPush::Off) {
            self.subscribed.store(false, Ordering::Release);
            self.subscribers.fetch_sub(1, Ordering::AcqRel);
        }
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

impl Drop for ConnectionSession<'_> {
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
    /// A line not finished within the request deadline of its first byte; holds the bytes
    /// received. The stream is left mid-line: close it.
    Overdue(usize),
    Eof,
}

/// A byte stream whose reads can be given a timeout: the socket, or (in tests) memory.
pub(crate) trait TimedRead: Read {
    fn set_read_timeout(&mut self, timeout: Duration) -> io::Result<()>;
}

impl TimedRead for UnixStream {
    fn set_read_timeout(&mut self, timeout: Duration) -> io::Result<()> {
        UnixStream::set_read_timeout(self, Some(timeout))
    }
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
    /// Between lines a read waits up to `idle`; once a line has begun, only until its deadline.
    idle: Duration,
    request_deadline: Duration,
    /// When the first byte of the current line arrived.
    line_started: Option<Instant>,
}

impl<R: TimedRead> LineReader<R> {
    pub(crate) fn new(inner: R, max_bytes: usize) -> Self {
        Self {
            inner,
            chunk: vec![0; READ_CHUNK_BYTES],
            chunk_pos: 0,
            chunk_len: 0,
            line: Vec::new(),
            max_bytes,
            skipped: None,
            idle: DEFAULT_IDLE_TIMEOUT,
            request_deadline: DEFAULT_REQUEST_DEADLINE,
            line_started: None,
        }
    }

    pub(crate) fn with_timeouts(mut self, idle: Duration, request_deadline: Duration) -> Self {
        self.idle = idle;
        self.request_deadline = request_deadline;
        self
    }

    /// Bytes of the current, unfinished line.
    fn partial_bytes(&self) -> usize {
        self.skipped.unwrap_or(self.line.len())
    }

    /// The next line. A read that times out between lines is an error of kind `WouldBlock` or
    /// `TimedOut` (the caller decides whether that is idling); a line that misses its deadline
    /// is [`ReadLine::Overdue`], however its bytes trickle in.
    pub(crate) fn next_line(&mut self) -> io::Result<ReadLine> {
        loop {
            if self.chunk_pos == self.chunk_len {
                let timeout = match self.line_started {
                    None => self.idle,
                    Some(started) => {
                        let left = self.request_deadline.saturating_sub(started.elapsed());
                        if left.is_zero() {
                            return Ok(ReadLine::Overdue(self.partial_bytes()));
                        }
                        left
                    }
                };
                self.inner.set_read_timeout(timeout)?;
                let n = match self.inner.read(&mut self.chunk) {
                    Ok(n) => n,
                    Err(err) if err.kind() == io::ErrorKind::Interrupted => continue,
                    Err(err)
                        if self.line_started.is_some()
                            && matches!(
                                err.kind(),
                                io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                            ) =>
                    {
                        continue;
                    }
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
                self.line_started.get_or_insert_with(Instant::now);
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
                self.line_started = (self.chunk_pos < self.chunk_len).then(Instant::now);
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

    impl TimedRead for Trickle<'_> {
        fn set_read_timeout(&mut self, _: Duration) -> io::Result<()> {
            Ok(())
        }
    }

    /// A peer that sends one byte per read, `pause` apart, and never a newline.
    struct Drip {
        pause: Duration,
    }

    impl Read for Drip {
        fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
            std::thread::sleep(self.pause);
            buf[0] = b'x';
            Ok(1)
        }
    }

    impl TimedRead for Drip {
        fn set_read_timeout(&mut self, _: Duration) -> io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn a_trickled_line_is_overdue_at_its_deadline() {
        let deadline = Duration::from_millis(200);
        let mut reader = LineReader::new(
            Drip {
                pause: Duration::from_millis(20),
            },
            1 << 20,
        )
        .with_timeouts(Duration::from_secs(60), deadline);
        let started = Instant::now();
        match reader.next_line() {
            Ok(ReadLine::Overdue(bytes)) => assert!(bytes >= 5, "{bytes}"),
            other => panic!("{other:?}"),
        }
        assert!(started.elapsed() >= deadline);
    }

    #[test]
    fn admission_caps_each_uid_and_keeps_the_last_slot_for_the_owner() {
        let options = ServerOptions {
            max_connections: 4,
            max_connections_per_uid: 2,
            ..ServerOptions::default()
        };
        assert!(admission(&options, false, 0, 0).is_ok());
        assert!(admission(&options, false, 1, 1).is_ok());
        let per_uid = admission(&options, false, 2, 2).unwrap_err();
        assert!(per_uid.contains("from this user"), "{per_uid}");
        assert!(admission(&options, false, 2, 0).is_ok());
        let reserved = admission(&options, false, 3, 0).unwrap_err();
        assert!(reserved.contains("kept for root"), "{reserved}");
        assert!(admission(&options, true, 3, 3).is_ok());
        assert!(admission(&options, true, 4, 0).is_err());
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
    fn user_database_groups_hold_the_primary_group() {
        let uid = rustix::process::getuid().as_raw();
        let gid = rustix::process::getgid().as_raw();
        let groups = user_groups(uid, gid);
        if nix::unistd::User::from_uid(nix::unistd::Uid::from_raw(uid))
            .ok()
            .flatten()
            .is_some()
        {
            assert!(groups.contains(&gid), "{groups:?} lacks {gid}");
        } else {
            assert!(groups.is_empty());
        }
        assert!(user_groups(u32::MAX - 7, 0).is_empty());
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
