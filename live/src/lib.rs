//! Watching the rig live: the relit video and everything behind it, while it runs.
//!
//! Two read-only views of the same frames, both off by default:
//! - a **Foxglove WebSocket server** (the official `foxglove` SDK, protocol `foxglove.sdk.v1`,
//!   the successor of `foxglove.websocket.v1` that the Foxglove app speaks) with the composite, the camera image, Δ in false colour, depth,
//!   the camera's calibration, the transforms of every frame the rig knows, a 3D scene of the
//!   virtual object and the lights, the lighting estimate and the status ([`channels`]);
//! - a **browser page** for a quick look without Foxglove: one HTML page that shows the live
//!   composite, the status and the lighting estimate ([`page`]).
//!
//! The render thread only offers frames ([`LiveView::offer`]): a frame is handed over when the
//! publisher is idle and dropped otherwise, so no viewer, however slow, can hold a frame back.
//! Encoding (JPEG, false colour) happens on the publisher's own thread, and only for the
//! channels someone subscribes to (the composite is always encoded for the page).
//!
//! Frames as published ([`frames`]): the world is the marker board's frame (glTF, +y up);
//! cameras are in the ROS optical convention (+z forward, +y down), as Foxglove and ROS expect
//! of an image's `frame_id`. Control stays on the daemon's Unix socket: neither view accepts a
//! command.

pub mod channels;
pub mod frames;
pub mod images;
pub mod page;

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender, TrySendError, bounded};
use relight_core::scene::Scene;
use relight_core::stream::MarkerSet;
use relight_core::{Frame, Image, LampState, Pose};
use serde::{Deserialize, Serialize};
use serde_json::Value;

use channels::Channels;
use page::PageState;

/// How the composite and the camera image travel to Foxglove.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ImageEncoding {
    /// `foxglove.CompressedImage`, JPEG at [`LiveViewSettings::jpeg_quality`].
    #[default]
    Jpeg,
    /// `foxglove.RawImage`, `rgb8`: lossless, about ten times the bytes.
    Raw,
}

/// Where the views listen and how they encode.
#[derive(Debug, Clone, PartialEq)]
pub struct LiveViewSettings {
    /// The Foxglove WebSocket server's address; port 0 picks a free one.
    pub foxglove: Option<SocketAddr>,
    /// The browser page's address; port 0 picks a free one.
    pub page: Option<SocketAddr>,
    pub image: ImageEncoding,
    /// JPEG quality, 1–100.
    pub jpeg_quality: u8,
    /// At most this many frames a second are published (the rest are dropped before encoding).
    pub max_rate_hz: f64,
}

impl Default for LiveViewSettings {
    fn default() -> Self {
        Self {
            foxglove: None,
            page: None,
            image: ImageEncoding::Jpeg,
            jpeg_quality: 80,
            max_rate_hz: 30.0,
        }
    }
}

/// One rendered frame and what it was rendered from, as the views publish it.
#[derive(Debug, Clone, Default)]
pub struct ViewFrame {
    pub seq: u64,
    /// Host time of the frame set, nanoseconds since the Unix epoch.
    pub host_ns: u64,
    /// Background + Δ, 8-bit RGB.
    pub composite: Image,
    /// Δ = L^ρ − L^μ, linear RGBA f16; zero-sized when the engine has none.
    pub delta: Image,
    pub color: Option<Arc<Frame<Image>>>,
    pub depth: Option<Arc<Frame<Image>>>,
    /// The scene the engine rendered: its camera, the virtual object(s) and the lights.
    pub scene: Option<Arc<Scene>>,
    /// The registered camera (glTF convention); `None` while untracked.
    pub world_from_camera: Option<Pose>,
    /// The markers detected in this frame set, in the colour camera's (glTF) frame.
    pub markers: Option<Arc<Frame<MarkerSet>>>,
    /// The tracked lamp, when the frame set has it.
    pub lamp: Option<LampState>,
}

/// What the views show besides frames, asked for at most twice a second.
pub trait Reports: Send + Sync {
    /// The daemon's status report, as `relightctl status --json` prints it.
    fn status(&self) -> Value;
    /// The lighting estimate, as `lights.get` returns it; `None` before the first.
    fn lighting(&self) -> Option<Value>;
}

/// Fixed poses of the rig, from its calibration (the world is the board's frame).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RigFrames {
    pub world_from_board: Option<Pose>,
    pub world_from_probe: Option<Pose>,
}

#[derive(Debug, thiserror::Error)]
pub enum LiveViewError {
    #[error("live view: the Foxglove server on {addr}: {source}")]
    Foxglove {
        addr: SocketAddr,
        source: foxglove::FoxgloveError,
    },
    #[error("live view: the page server on {addr}: {message}")]
    Page { addr: SocketAddr, message: String },
    #[error("live view: jpeg_quality must be 1-100, not {0}")]
    Quality(u8),
    #[error("live view: {0}")]
    Io(#[from] std::io::Error),
}

/// The running views. Dropping it stops the publisher and both servers.
pub struct LiveView {
    /// The channels' and the server's context: they hold it weakly, so it lives here.
    context: Option<Arc<foxglove::Context>>,
    frames: Option<Sender<ViewFrame>>,
    publisher: Option<JoinHandle<()>>,
    foxglove: Option<foxglove::WebSocketServerHandle>,
    page: Option<page::PageServer>,
    foxglove_addr: Option<SocketAddr>,
    min_interval: Duration,
    last_offer: Mutex<Option<Instant>>,
}

impl std::fmt::Debug for LiveView {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveView")
            .field("foxglove", &self.foxglove_addr)
            .field("page", &self.page_addr())
            .finish_non_exhaustive()
    }
}

impl LiveView {
    /// Start the views `settings` asks for (none: a view that drops every frame).
    pub fn start(
        settings: &LiveViewSettings,
        rig: RigFrames,
        reports: Arc<dyn Reports>,
    ) -> Result<Self, LiveViewError> {
        if !(1..=100).contains(&settings.jpeg_quality) {
            return Err(LiveViewError::Quality(settings.jpeg_quality));
        }
        let context = foxglove::Context::new();
        let mut foxglove_addr = None;
        let foxglove = match settings.foxglove {
            Some(addr) => {
                let handle = context
                    .websocket_server()
                    .name("relightd")
                    .bind(addr.ip().to_string(), addr.port())
                    .start_blocking()
                    .map_err(|source| LiveViewError::Foxglove { addr, source })?;
                let bound = SocketAddr::new(addr.ip(), handle.port());
                tracing::info!(url = %format!("ws://{bound}"), "Foxglove live view");
                foxglove_addr = Some(bound);
                Some(handle)
            }
            None => None,
        };
        let state = Arc::new(PageState::default());
        let page = settings
            .page
            .map(|addr| page::PageServer::start(addr, Arc::clone(&state)))
            .transpose()?;
        if let Some(page) = &page {
            tracing::info!(url = %format!("http://{}/", page.addr()), "live view page");
        }
        let (frames, publisher) = if foxglove.is_some() || page.is_some() {
            let (sender, receiver) = bounded(1);
            let publisher = Publisher {
                channels: Channels::new(&context, settings.image, rig),
                jpeg_quality: settings.jpeg_quality,
                state,
                reports,
                last_report: None,
            };
            let thread = std::thread::Builder::new()
                .name("live-view".into())
                .spawn(move || publisher.run(receiver))?;
            (Some(sender), Some(thread))
        } else {
            (None, None)
        };
        Ok(Self {
            context: Some(context),
            frames,
            publisher,
            foxglove,
            page,
            foxglove_addr,
            min_interval: Duration::from_secs_f64(1.0 / settings.max_rate_hz.max(0.1)),
            last_offer: Mutex::new(None),
        })
    }

    /// A view that publishes nothing.
    pub fn disabled() -> Self {
        Self {
            context: None,
            frames: None,
            publisher: None,
            foxglove: None,
            page: None,
            foxglove_addr: None,
            min_interval: Duration::MAX,
            last_offer: Mutex::new(None),
        }
    }

    /// Whether a frame offered now would be taken: a view runs, the rate allows one, and the
    /// publisher is idle. The render thread asks before it copies a frame.
    pub fn wants_frame(&self) -> bool {
        let Some(frames) = &self.frames else {
            return false;
        };
        let last = *self.last_offer.lock().unwrap_or_else(|e| e.into_inner());
        frames.is_empty() && last.is_none_or(|t| t.elapsed() >= self.min_interval)
    }

    /// Hand `frame` to the publisher, or drop it when the publisher is still busy.
    pub fn offer(&self, frame: ViewFrame) {
        let Some(frames) = &self.frames else {
            return;
        };
        match frames.try_send(frame) {
            Ok(()) => {
                *self.last_offer.lock().unwrap_or_else(|e| e.into_inner()) = Some(Instant::now());
            }
            Err(TrySendError::Full(_)) => {}
            Err(TrySendError::Disconnected(_)) => {
                tracing::warn!("the live view's publisher stopped; frames are no longer published")
            }
        }
    }

    /// The Foxglove server's address as bound (its port when asked for port 0).
    pub fn foxglove_addr(&self) -> Option<SocketAddr> {
        self.foxglove_addr
    }

    /// The page server's address as bound.
    pub fn page_addr(&self) -> Option<SocketAddr> {
        self.page.as_ref().map(page::PageServer::addr)
    }

    /// Foxglove clients connected now.
    pub fn foxglove_clients(&self) -> usize {
        self.foxglove.as_ref().map_or(0, |f| f.client_count())
    }
}

impl Drop for LiveView {
    fn drop(&mut self) {
        self.frames = None;
        if let Some(publisher) = self.publisher.take()
            && publisher.join().is_err()
        {
            tracing::error!("the live view's publisher panicked");
        }
        if let Some(foxglove) = self.foxglove.take() {
            // The handle's runner finishes closing the clients in the background.
            drop(foxglove.stop());
        }
        self.context = None;
    }
}

/// How often the status and the lighting estimate are asked for.
const REPORT_INTERVAL: Duration = Duration::from_millis(500);

/// The publisher thread: encodes frames and logs them to the subscribed channels and the page.
struct Publisher {
    channels: Channels,
    jpeg_quality: u8,
    state: Arc<PageState>,
    reports: Arc<dyn Reports>,
    last_report: Option<Instant>,
}

impl Publisher {
    fn run(mut self, frames: Receiver<ViewFrame>) {
        loop {
            match frames.recv_timeout(REPORT_INTERVAL) {
                Ok(frame) => self.publish(&frame),
                Err(crossbeam_channel::RecvTimeoutError::Timeout) => {}
                Err(crossbeam_channel::RecvTimeoutError::Disconnected) => return,
            }
            if self
                .last_report
                .is_none_or(|t| t.elapsed() >= REPORT_INTERVAL)
            {
                self.last_report = Some(Instant::now());
                let status = self.reports.status();
                let lighting = self.reports.lighting();
                self.channels.reports(&status, lighting.as_ref());
                self.state.set_reports(status, lighting);
            }
        }
    }

    fn publish(&mut self, frame: &ViewFrame) {
        let composite_jpeg = images::jpeg(&frame.composite, self.jpeg_quality)
            .inspect_err(|error| tracing::warn!(%error, "composite not encoded"))
            .ok();
        self.channels
            .frame(frame, composite_jpeg.as_deref(), self.jpeg_quality);
        if let Some(jpeg) = composite_jpeg {
            self.state.set_composite(frame.seq, jpeg);
        }
    }
}
