//! Shared-memory transport for multi-channel streams, built on [iceoryx2] 0.10
//! (zero-copy, daemon-less IPC).
//!
//! # Wire contract
//!
//! Acquisition software in Python, C++ or Rust talks to `jointid` by following these
//! rules. iceoryx2 checks type names, sizes, alignments and QoS when a port opens a
//! service: a mismatch makes `open` fail with a clear error instead of corrupting
//! data.
//!
//! ## Services
//!
//! Each stream is one **publish-subscribe** service plus one **event** service with
//! the **same name**. iceoryx2 keeps services of different messaging patterns apart,
//! so a shared name is allowed, and the upstream `event_based_communication` example
//! uses it too.
//!
//! | stream        | service name                        | direction              |
//! |---------------|-------------------------------------|------------------------|
//! | excitation    | `<session>/jointid/excitation`      | acquisition -> jointid |
//! | response      | `<session>/jointid/response`        | acquisition -> jointid |
//! | residuals     | `<session>/jointid/residuals`       | jointid -> viewers     |
//! | parameters    | `<session>/jointid/parameters`      | jointid -> viewers     |
//! | diagnostics   | `<session>/jointid/diagnostics`     | jointid -> viewers     |
//!
//! `<session>` defaults to `default`. It lets two independent sessions share one
//! machine. It must be non-empty and may use only `[A-Za-z0-9_.-]`.
//!
//! iceoryx2's own `global.prefix` config entry (default `iox2_`) is the prefix of
//! *every* file that iceoryx2 creates (in `/dev/shm` and `/tmp/iceoryx2`). Processes
//! with different prefixes cannot see each other at all. [`ShmOptions::global_prefix`]
//! sets it (`None` keeps the value from the iceoryx2 config file, which is normally
//! `iox2_`). Tests use one prefix per run. A foreign process must use the same
//! prefix, either through its `iceoryx2.toml` (`[global] prefix = "..."`) or through
//! its config API.
//!
//! ## Payload
//!
//! * Payload: a dynamic slice of `f64` holding one value per channel, in channel order,
//!   in SI units. The payload type name is `f64`: `TypeVariant::Dynamic`, size 8,
//!   alignment 8.
//! * User header: [`FrameHeader`], `#[repr(C)]`, 24 bytes, alignment 8, type name
//!   **`jointid::FrameHeader`** ([`FRAME_HEADER_TYPE_NAME`]):
//!
//!   | offset | field      | type | meaning                                            |
//!   |--------|------------|------|----------------------------------------------------|
//!   | 0      | `sample`   | u64  | sample index; +1 per frame, gaps mean lost frames  |
//!   | 8      | `t_ns`     | u64  | timestamp in ns (the publisher picks the epoch)    |
//!   | 16     | `channels` | u32  | number of `f64` values in the payload              |
//!   | 20     | `flags`    | u32  | reserved; write 0, and readers ignore it           |
//!
//! * Python (`iceoryx2` on PyPI) declares the same types like this:
//!   ```text
//!   class FrameHeader(ctypes.Structure):
//!       _fields_ = [("sample", ctypes.c_uint64), ("t_ns", ctypes.c_uint64),
//!                   ("channels", ctypes.c_uint32), ("flags", ctypes.c_uint32)]
//!       @staticmethod
//!       def type_name(): return "jointid::FrameHeader"
//!   service = (node.service_builder(iox2.ServiceName.new("default/jointid/response"))
//!              .publish_subscribe(iox2.Slice[ctypes.c_double])   # type name "f64"
//!              .user_header(FrameHeader)
//!              # ... same QoS as below ...
//!              .open_or_create())
//!   ```
//!   In C++, use `iox2::Slice<double>` and give the header struct
//!   `static constexpr const char* IOX2_TYPE_NAME = "jointid::FrameHeader";`.
//! * Known upstream bug (iceoryx2 issue #1533): a **Python subscriber** gets the slice
//!   length in *bytes*, not elements, so `len(payload)` is `8 * channels`. Python
//!   readers should use `header.channels`. That is one reason the header carries it.
//!   Rust and C++ readers are not affected, and Python *publishers* write correct data.
//!
//! ## Quality of service
//!
//! The publish-subscribe service is opened or created with the values from
//! [`ShmOptions`] (defaults in parentheses). Any other process must use the same
//! values, or only open an existing service:
//!
//! * `subscriber_max_buffer_size` (default 8192): at 51.2 kHz that is 160 ms of slack
//!   per subscriber. The iceoryx2 default of 2 samples drops data as soon as the
//!   reader is descheduled for 40 µs.
//! * `enable_safe_overflow` (default **false**): iceoryx2's default (`true`) silently
//!   *overwrites the oldest* sample when a buffer is full. With `false`, the publisher
//!   applies backpressure instead, which is right for identification, where every
//!   sample counts. The value must match exactly between creator and opener.
//! * `history_size` (default 0): a late subscriber starts with live data, not a stale
//!   burst.
//! * `max_subscribers` (default 4) and `max_publishers` (default 2): `max_publishers`
//!   leaves room for a restarted acquisition program while the crashed one has not
//!   been cleaned up yet.
//! * Publisher ports: `initial_max_slice_len` = `max_channels` (default 64) with
//!   `AllocationStrategy::Static`, so a wider frame is rejected with
//!   [`ShmError::InvalidFrame`]. A growing strategy such as `PowerOfTwo` makes
//!   iceoryx2 use *dynamic* data segments. A subscriber maps those lazily, so frames
//!   that a publisher sent just before it dropped were lost ("Lost chunk" warning,
//!   seen in our tests). A static segment is mapped as soon as the subscriber
//!   connects.
//! * Backpressure is `RetryUntilDelivered`, bounded by
//!   [`ShmOptions::backpressure_timeout`] (default 20 ms) per sample and subscriber.
//!   After that, the sample is discarded *for that subscriber only*, and the
//!   subscriber sees a gap in `sample`. The subscriber is then treated as stalled
//!   while its buffer stays full and for [`ShmOptions::stall_hold`] (default 2 s) after
//!   the last time it was found full: its samples are discarded without waiting, so a
//!   hung or crashed reader costs the publisher one timeout in all (it used to cost 200 ms
//!   every 2 s: p99 of the acquisition loop 214 ms). The 20 ms add to the 160 ms of the
//!   subscriber buffer at 51.2 kHz as the slack a live reader has before it loses
//!   samples. Dead-node cleanup is also triggered then. Foreign publishers should use
//!   `RetryUntilDelivered` or `DiscardData`.
//! * Memory: each publisher preallocates
//!   `max_subscribers * (buffer + 2) + history + 2` chunks of `72 + 8 * max_channels`
//!   bytes (rounded up to 16). With the defaults that is about 19 MiB of `/dev/shm`
//!   per publisher, and only pages that are touched cost RAM.
//!
//! ## Notification and liveness
//!
//! * After each send, or after each batch of sends, a publisher calls `notify()` on a
//!   notifier of the event service. The event id does not matter. The subscriber thread
//!   waits on its `Listener` in a `WaitSet` (a `WaitSet` can wait on a listener but not
//!   on a subscriber), so it does not spin. It also wakes every
//!   [`ShmOptions::poll_interval`] (default 25 ms), which bounds the stop latency and
//!   covers a publisher that forgets to notify.
//! * Publisher presence comes from the service's dynamic config
//!   (`number_of_publishers()`). When it drops to 0, the subscriber first drains what
//!   is left and then emits [`ShmEvent::PublisherGone`]. When it rises again, or the
//!   first frame arrives, it emits [`ShmEvent::PublisherAppeared`].
//! * A subscriber *connects* to a new publisher on its next `receive` or
//!   `update_connections`. The subscriber thread does this as soon as it sees the
//!   publisher count rise, and only then emits `PublisherAppeared`. Until a subscriber
//!   has connected, the publisher can queue at most `subscriber_buffer` frames for it
//!   (160 ms at 51.2 kHz). It drops anything beyond that, and the loss shows up as a
//!   gap in `sample`. Frames sent by a publisher that is dropped *before* the
//!   subscriber connected are lost. After the subscriber connected, frames that are
//!   still queued survive the publisher.
//! * A restart that completes within one `poll_interval` may produce no
//!   `PublisherGone`/`PublisherAppeared` pair. Frames keep flowing either way, and
//!   gaps are counted separately for each publisher.
//! * A publisher that *crashes* stays registered until someone removes the stale
//!   resources of its dead node. The subscriber thread does that itself
//!   (`PortFactory::try_cleanup_dead_nodes`) once the stream has been silent for
//!   [`ShmOptions::liveness_interval`] (default 500 ms). [`cleanup_dead_nodes`] does
//!   the same for the whole prefix. iceoryx2 also cleans dead nodes whenever a new
//!   node is created.
//!
//! ## Threads
//!
//! `ipc::Service` ports are not `Send`. Each port therefore lives on its own thread
//! ([`spawn_subscriber`], [`spawn_publisher`]), which exchanges data with the rest of
//! the program through crossbeam channels. [`FramePublisher`] and [`FrameSubscriber`]
//! are the same machinery without a thread, for a program's own loop and for tests.
//!
//! [iceoryx2]: https://github.com/eclipse-iceoryx/iceoryx2

use std::fmt::Debug;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, SendTimeoutError, Sender};
use iceoryx2::config::Config;
use iceoryx2::identifiers::UniquePublisherId;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::port::{BackpressureAction, BackpressureInfo};
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::event::PortFactory as EventService;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubService;

/// One sample of a multi-channel stream. `values` are in channel order (SI units).
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub sample: u64,
    pub t_ns: u64,
    pub values: Vec<f64>,
}

/// The iceoryx2 type name of [`FrameHeader`]; other languages must use exactly this.
pub const FRAME_HEADER_TYPE_NAME: &str = "jointid::FrameHeader";
/// The iceoryx2 type name of one payload element (`f64`, `ctypes.c_double`, `double`).
pub const PAYLOAD_ELEMENT_TYPE_NAME: &str = "f64";
/// The streams of the contract, the last path element of each service name.
pub const STREAMS: [&str; 5] = [
    "excitation",
    "response",
    "residuals",
    "parameters",
    "diagnostics",
];

/// User header in front of every payload (`#[repr(C)]`, 24 bytes, alignment 8).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
#[repr(C)]
#[type_name("jointid::FrameHeader")]
pub struct FrameHeader {
    /// Sample index. It is expected to increase by one per frame, and a jump means lost frames.
    pub sample: u64,
    /// Timestamp in nanoseconds; the epoch is the publisher's choice.
    pub t_ns: u64,
    /// Number of `f64` elements in the payload slice.
    pub channels: u32,
    /// Reserved, written as 0 and ignored by readers.
    pub flags: u32,
}

/// Errors of the shared-memory transport.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ShmError {
    /// A field of [`ShmOptions`] is invalid.
    #[error("invalid shared-memory option: {0}")]
    InvalidOption(String),
    /// The stream name is not one of [`STREAMS`].
    #[error(
        "unknown stream `{0}` (expected one of excitation, response, residuals, parameters, diagnostics)"
    )]
    UnknownStream(String),
    /// A frame cannot be encoded.
    #[error("invalid frame: {0}")]
    InvalidFrame(String),
    /// An iceoryx2 call failed.
    #[error("iceoryx2 {what} failed: {detail}")]
    Iceoryx { what: &'static str, detail: String },
    /// The worker thread could not be started or died before it was ready.
    #[error("shared-memory worker thread: {0}")]
    Thread(String),
}

fn iox<E: Debug>(what: &'static str) -> impl FnOnce(E) -> ShmError {
    move |e| ShmError::Iceoryx {
        what,
        detail: format!("{e:?}"),
    }
}

/// Options of the transport. `Default` gives the values documented in the module docs
/// (chosen for 51.2 kHz acquisition).
#[derive(Debug, Clone, PartialEq)]
pub struct ShmOptions {
    /// Session name, the first element of every service name (`<session>/jointid/<stream>`).
    pub session: String,
    /// iceoryx2 `global.prefix` (prefix of every shm/file resource). `None` keeps the
    /// iceoryx2 config value (normally `iox2_`). Only processes with the same prefix meet.
    pub global_prefix: Option<String>,
    /// Service `subscriber_max_buffer_size`, and the buffer of our subscribers, in frames.
    pub subscriber_buffer: usize,
    /// Service `history_size`: frames replayed to a late subscriber.
    pub history: usize,
    /// Publisher `initial_max_slice_len`: the most values a frame may carry (static
    /// allocation; a frame with more values is rejected).
    pub max_channels: usize,
    /// Service `max_subscribers`.
    pub max_subscribers: usize,
    /// Service `max_publishers`.
    pub max_publishers: usize,
    /// Service `enable_safe_overflow` (true = overwrite the oldest sample when full).
    pub safe_overflow: bool,
    /// How long one send waits for a full subscriber before discarding the sample for
    /// it. `None` waits forever (pure `RetryUntilDelivered`). Unused with `safe_overflow`.
    pub backpressure_timeout: Option<Duration>,
    /// After a backpressure timeout, how long the subscriber counts as stalled, so
    /// that samples for it are discarded without waiting.
    pub stall_hold: Duration,
    /// Upper bound on how long the subscriber thread sleeps between checks of the
    /// stop flag and the publisher count (at most 100 ms).
    pub poll_interval: Duration,
    /// Silence after which the subscriber thread runs dead-node cleanup, to detect a
    /// crashed publisher.
    pub liveness_interval: Duration,
    /// The publisher thread sends at most this many queued frames per notification.
    pub max_batch: usize,
}

impl Default for ShmOptions {
    fn default() -> Self {
        Self {
            session: "default".to_owned(),
            global_prefix: None,
            subscriber_buffer: 8192,
            history: 0,
            max_channels: 64,
            max_subscribers: 4,
            max_publishers: 2,
            safe_overflow: false,
            backpressure_timeout: Some(Duration::from_millis(20)),
            stall_hold: Duration::from_secs(2),
            poll_interval: Duration::from_millis(25),
            liveness_interval: Duration::from_millis(500),
            max_batch: 512,
        }
    }
}

impl ShmOptions {
    /// Checks the options. All public constructors call this first.
    pub fn validate(&self) -> Result<(), ShmError> {
        let bad = |m: String| Err(ShmError::InvalidOption(m));
        if self.session.is_empty()
            || !self
                .session
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'))
        {
            return bad(format!(
                "session {:?} must be non-empty and use only [A-Za-z0-9_.-]",
                self.session
            ));
        }
        if let Some(p) = &self.global_prefix
            && (p.is_empty()
                || !p
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.')))
        {
            return bad(format!(
                "global_prefix {p:?} must be non-empty and use only [A-Za-z0-9_.-]"
            ));
        }
        if self.subscriber_buffer == 0 || self.max_channels == 0 || self.max_batch == 0 {
            return bad("subscriber_buffer, max_channels and max_batch must be >= 1".into());
        }
        if self.max_subscribers == 0 || self.max_publishers == 0 {
            return bad("max_subscribers and max_publishers must be >= 1".into());
        }
        if !self.safe_overflow && self.history > self.subscriber_buffer {
            return bad("history must not exceed subscriber_buffer without safe_overflow".into());
        }
        if self.poll_interval.is_zero() || self.poll_interval > Duration::from_millis(100) {
            return bad("poll_interval must be in (0, 100 ms]".into());
        }
        Ok(())
    }

    /// The iceoryx2 service name of `stream` in this session.
    pub fn service_name(&self, stream: &str) -> Result<String, ShmError> {
        check_stream(stream)?;
        Ok(format!("{}/jointid/{stream}", self.session))
    }

    /// The iceoryx2 config: the global config (from `iceoryx2.toml` if one exists)
    /// with `global.prefix` replaced when [`ShmOptions::global_prefix`] is set.
    pub fn iceoryx_config(&self) -> Result<Config, ShmError> {
        let mut config = Config::global_config().clone();
        if let Some(prefix) = &self.global_prefix {
            config.global.prefix = FileName::new(prefix.as_bytes())
                .map_err(|e| ShmError::InvalidOption(format!("global_prefix {prefix:?}: {e:?}")))?;
        }
        Ok(config)
    }
}

fn check_stream(stream: &str) -> Result<(), ShmError> {
    if STREAMS.contains(&stream) {
        Ok(())
    } else {
        Err(ShmError::UnknownStream(stream.to_owned()))
    }
}

/// What a subscriber thread sends to its consumer.
#[derive(Debug, Clone, PartialEq)]
pub enum ShmEvent {
    Frame(Frame),
    /// The number of publishers dropped to 0, after the remaining frames were delivered.
    PublisherGone,
    /// A publisher is present; this comes before its first frame.
    PublisherAppeared,
    /// A non-fatal error; the thread keeps running.
    Error(String),
}

/// Counters of a subscriber (thread).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SubscriberStats {
    pub frames_received: u64,
    /// Frames missing according to gaps in `sample`, counted per publisher.
    pub drops_detected: u64,
    /// Frames whose `header.channels` differed from the payload length; the payload length is used.
    pub header_mismatches: u64,
    /// Largest depth of the outgoing crossbeam channel seen right after a send.
    pub max_queue_depth: usize,
    pub publisher_appeared: u64,
    pub publisher_gone: u64,
    pub errors: u64,
}

/// Counters of a publisher (thread).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct PublisherStats {
    pub frames_published: u64,
    /// Frames that reached no subscriber at all.
    pub frames_unsubscribed: u64,
    /// Per-subscriber deliveries dropped by the backpressure timeout or a stall.
    pub backpressure_discards: u64,
    pub notifications: u64,
    pub notify_errors: u64,
    /// Largest depth of the incoming crossbeam channel (this frame included).
    pub max_queue_depth: usize,
}

type FrameService = PubSubService<ipc::Service, [f64], FrameHeader>;

fn create_node(config: &Config, role: &str, stream: &str) -> Result<Node<ipc::Service>, ShmError> {
    let name = NodeName::new(&format!("jointid-{role}-{stream}")).map_err(iox("node name"))?;
    NodeBuilder::new()
        .name(&name)
        .config(config)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
        .map_err(iox("node creation"))
}

fn open_services(
    node: &Node<ipc::Service>,
    opts: &ShmOptions,
    stream: &str,
) -> Result<(FrameService, EventService<ipc::Service>), ShmError> {
    let name = ServiceName::new(&opts.service_name(stream)?).map_err(iox("service name"))?;
    let pubsub = node
        .service_builder(&name)
        .publish_subscribe::<[f64]>()
        .user_header::<FrameHeader>()
        .subscriber_max_buffer_size(opts.subscriber_buffer)
        .history_size(opts.history)
        .enable_safe_overflow(opts.safe_overflow)
        .max_subscribers(opts.max_subscribers)
        .max_publishers(opts.max_publishers)
        .open_or_create()
        .map_err(iox("publish-subscribe service open_or_create"))?;
    let event = node
        .service_builder(&name)
        .event()
        .open_or_create()
        .map_err(iox("event service open_or_create"))?;
    Ok((pubsub, event))
}

/// Decides what a publisher does when a subscriber's buffer is full.
#[derive(Debug)]
struct StallTracker {
    timeout: Duration,
    hold: Duration,
    stalled: Mutex<Vec<(u128, Instant)>>,
    discards: AtomicU64,
    /// Times a subscriber was waited for up to the timeout and then declared stalled.
    stall_events: AtomicU64,
    cleanup_requested: AtomicBool,
}

impl StallTracker {
    fn decide(&self, info: &BackpressureInfo) -> BackpressureAction {
        let now = Instant::now();
        let mut stalled = self.stalled.lock().unwrap_or_else(PoisonError::into_inner);
        stalled.retain(|(_, since)| now.duration_since(*since) < self.hold);
        if let Some(entry) = stalled
            .iter_mut()
            .find(|(id, _)| *id == info.receiver_port_id)
        {
            // Still full: still stalled. The hold counts from the last full buffer, so a
            // hung reader is waited for once, not once per hold.
            entry.1 = now;
            self.discards.fetch_add(1, Ordering::Relaxed);
            return BackpressureAction::DiscardData;
        }
        if info.elapsed_time >= self.timeout {
            stalled.push((info.receiver_port_id, now));
            self.stall_events.fetch_add(1, Ordering::Relaxed);
            self.discards.fetch_add(1, Ordering::Relaxed);
            self.cleanup_requested.store(true, Ordering::Relaxed);
            return BackpressureAction::DiscardData;
        }
        BackpressureAction::Retry
    }
}

/// A publisher + notifier for one stream, for use in the caller's own loop (not `Send`).
#[derive(Debug)]
pub struct FramePublisher {
    // Field order = drop order: ports before services before the node.
    notifier: Notifier<ipc::Service>,
    publisher: Publisher<ipc::Service, [f64], FrameHeader>,
    _event: EventService<ipc::Service>,
    pubsub: FrameService,
    _node: Node<ipc::Service>,
    stalls: Arc<StallTracker>,
}

impl FramePublisher {
    /// Creates a node, opens or creates the stream's services, and creates the ports.
    pub fn new(opts: &ShmOptions, stream: &str) -> Result<Self, ShmError> {
        opts.validate()?;
        check_stream(stream)?;
        let config = opts.iceoryx_config()?;
        let node = create_node(&config, "pub", stream)?;
        let (pubsub, event) = open_services(&node, opts, stream)?;
        let stalls = Arc::new(StallTracker {
            timeout: opts.backpressure_timeout.unwrap_or(Duration::MAX),
            hold: opts.stall_hold,
            stalled: Mutex::new(Vec::new()),
            discards: AtomicU64::new(0),
            stall_events: AtomicU64::new(0),
            cleanup_requested: AtomicBool::new(false),
        });
        let mut builder = pubsub
            .publisher_builder()
            .initial_max_slice_len(opts.max_channels)
            .allocation_strategy(AllocationStrategy::Static)
            .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered);
        if opts.backpressure_timeout.is_some() {
            let tracker = Arc::clone(&stalls);
            builder = builder
                .set_backpressure_handler(move |info: &BackpressureInfo| tracker.decide(info));
        }
        let publisher = builder.create().map_err(iox("publisher creation"))?;
        let notifier = event
            .notifier_builder()
            .create()
            .map_err(iox("notifier creation"))?;
        Ok(Self {
            notifier,
            publisher,
            _event: event,
            pubsub,
            _node: node,
            stalls,
        })
    }

    /// Publishes one frame without notifying. Returns the number of subscribers reached.
    pub fn publish(&self, frame: &Frame) -> Result<usize, ShmError> {
        let max = self.publisher.initial_max_slice_len();
        if frame.values.len() > max {
            return Err(ShmError::InvalidFrame(format!(
                "{} values exceed max_channels = {max}",
                frame.values.len()
            )));
        }
        let channels = u32::try_from(frame.values.len()).map_err(|_| {
            ShmError::InvalidFrame(format!("{} channels exceed u32", frame.values.len()))
        })?;
        let mut sample = self
            .publisher
            .loan_slice_uninit(frame.values.len())
            .map_err(iox("loan"))?;
        *sample.user_header_mut() = FrameHeader {
            sample: frame.sample,
            t_ns: frame.t_ns,
            channels,
            flags: 0,
        };
        let delivered = sample
            .write_from_slice(&frame.values)
            .send()
            .map_err(iox("send"))?;
        if self.stalls.cleanup_requested.swap(false, Ordering::Relaxed) {
            // A subscriber timed out: if its process died, remove it for good.
            self.pubsub.try_cleanup_dead_nodes();
        }
        Ok(delivered)
    }

    /// Wakes all listeners of the stream (call after a frame or a batch).
    pub fn notify(&self) -> Result<(), ShmError> {
        self.notifier.notify().map(|_| ()).map_err(iox("notify"))
    }

    /// Publishes all frames, then notifies once. Returns the summed deliveries.
    pub fn publish_batch(&self, frames: &[Frame]) -> Result<usize, ShmError> {
        let mut delivered = 0;
        for frame in frames {
            delivered += self.publish(frame)?;
        }
        self.notify()?;
        Ok(delivered)
    }

    /// Number of subscribers currently registered with the service.
    pub fn subscriber_count(&self) -> usize {
        self.pubsub.dynamic_config().number_of_subscribers()
    }

    /// Waits (polling every millisecond) until at least `n` subscribers exist.
    pub fn wait_for_subscribers(&self, n: usize, timeout: Duration) -> bool {
        let deadline = Instant::now() + timeout;
        loop {
            if self.subscriber_count() >= n {
                return true;
            }
            if Instant::now() >= deadline {
                return false;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    /// Per-subscriber deliveries discarded by the backpressure timeout so far.
    pub fn backpressure_discards(&self) -> u64 {
        self.stalls.discards.load(Ordering::Relaxed)
    }

    /// Times a full subscriber was waited for (up to the backpressure timeout) and then
    /// declared stalled: each costs the publisher one timeout.
    pub fn stall_events(&self) -> u64 {
        self.stalls.stall_events.load(Ordering::Relaxed)
    }
}

#[derive(Debug, Default)]
struct GapTracker {
    last: Vec<(UniquePublisherId, u64)>,
    stats: SubscriberStats,
}

impl GapTracker {
    fn observe(&mut self, origin: UniquePublisherId, sample: u64) {
        self.stats.frames_received += 1;
        if let Some(entry) = self.last.iter_mut().find(|(o, _)| *o == origin) {
            if sample > entry.1 {
                self.stats.drops_detected += sample - entry.1 - 1;
            }
            // sample <= last: the counter was reset; start over without counting drops.
            entry.1 = sample;
        } else {
            if self.last.len() >= 16 {
                self.last.remove(0);
            }
            self.last.push((origin, sample));
        }
    }
}

#[derive(Debug)]
struct SubPorts {
    listener: Listener<ipc::Service>,
    subscriber: Subscriber<ipc::Service, [f64], FrameHeader>,
    _event: EventService<ipc::Service>,
    pubsub: FrameService,
    _node: Node<ipc::Service>,
}

impl SubPorts {
    fn receive(&self, tracker: &mut GapTracker) -> Result<Option<Frame>, ShmError> {
        let Some(sample) = self.subscriber.receive().map_err(iox("receive"))? else {
            return Ok(None);
        };
        let header = *sample.user_header();
        let values = sample.payload().to_vec();
        let origin = sample.origin();
        drop(sample);
        if header.channels as usize != values.len() {
            tracker.stats.header_mismatches += 1;
        }
        tracker.observe(origin, header.sample);
        Ok(Some(Frame {
            sample: header.sample,
            t_ns: header.t_ns,
            values,
        }))
    }

    fn publisher_count(&self) -> usize {
        self.pubsub.dynamic_config().number_of_publishers()
    }
}

/// A subscriber + listener for one stream, for use in the caller's own loop (not `Send`).
#[derive(Debug)]
pub struct FrameSubscriber {
    ports: SubPorts,
    tracker: GapTracker,
}

impl FrameSubscriber {
    /// Creates a node, opens or creates the stream's services, and creates the ports.
    /// Frames published after this returns are delivered.
    pub fn new(opts: &ShmOptions, stream: &str) -> Result<Self, ShmError> {
        opts.validate()?;
        check_stream(stream)?;
        let config = opts.iceoryx_config()?;
        let node = create_node(&config, "sub", stream)?;
        let (pubsub, event) = open_services(&node, opts, stream)?;
        let subscriber = pubsub
            .subscriber_builder()
            .buffer_size(opts.subscriber_buffer)
            .create()
            .map_err(iox("subscriber creation"))?;
        let listener = event
            .listener_builder()
            .create()
            .map_err(iox("listener creation"))?;
        Ok(Self {
            ports: SubPorts {
                listener,
                subscriber,
                _event: event,
                pubsub,
                _node: node,
            },
            tracker: GapTracker::default(),
        })
    }

    /// Takes the next frame, if any (never blocks).
    pub fn try_recv(&mut self) -> Result<Option<Frame>, ShmError> {
        self.ports.receive(&mut self.tracker)
    }

    /// Blocks on the listener until a publisher notifies or `timeout` passes, and
    /// consumes the pending notifications. Returns whether a notification arrived.
    /// Drain with [`FrameSubscriber::try_recv`] *before* waiting.
    pub fn wait(&self, timeout: Duration) -> Result<bool, ShmError> {
        self.ports
            .listener
            .timed_wait(|_| {}, timeout)
            .map(|n| n > 0)
            .map_err(iox("listener wait"))
    }

    /// Number of publishers currently registered with the service.
    pub fn publisher_count(&self) -> usize {
        self.ports.publisher_count()
    }

    /// Removes the stale resources of dead nodes attached to this stream's service.
    pub fn cleanup_dead_nodes(&self) -> usize {
        usize::try_from(self.ports.pubsub.try_cleanup_dead_nodes().cleanups).unwrap_or(usize::MAX)
    }

    /// Counters so far.
    pub fn stats(&self) -> SubscriberStats {
        self.tracker.stats.clone()
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Flow {
    Continue,
    Stop,
}

struct Forwarder<'a> {
    tx: &'a Sender<ShmEvent>,
    stop: &'a AtomicBool,
    poll: Duration,
    max_depth: usize,
}

impl Forwarder<'_> {
    /// Sends into the bounded channel; waits while it is full, but gives up when the
    /// stop flag is set or the receiver is gone.
    fn send(&mut self, mut event: ShmEvent) -> Flow {
        loop {
            match self.tx.send_timeout(event, self.poll) {
                Ok(()) => {
                    self.max_depth = self.max_depth.max(self.tx.len());
                    return Flow::Continue;
                }
                Err(SendTimeoutError::Timeout(back)) => {
                    if self.stop.load(Ordering::Acquire) {
                        return Flow::Stop;
                    }
                    event = back;
                }
                Err(SendTimeoutError::Disconnected(_)) => return Flow::Stop,
            }
        }
    }
}

/// Drains the subscriber. Returns the flow and the number of frames forwarded.
fn drain(
    ports: &SubPorts,
    tracker: &mut GapTracker,
    fwd: &mut Forwarder<'_>,
    present: &mut bool,
) -> (Flow, usize) {
    let mut n = 0;
    loop {
        if fwd.stop.load(Ordering::Acquire) {
            return (Flow::Stop, n);
        }
        match ports.receive(tracker) {
            Ok(Some(frame)) => {
                if !*present {
                    *present = true;
                    tracker.stats.publisher_appeared += 1;
                    if fwd.send(ShmEvent::PublisherAppeared) == Flow::Stop {
                        return (Flow::Stop, n);
                    }
                }
                n += 1;
                if fwd.send(ShmEvent::Frame(frame)) == Flow::Stop {
                    return (Flow::Stop, n);
                }
            }
            Ok(None) => return (Flow::Continue, n),
            Err(e) => {
                tracker.stats.errors += 1;
                return (fwd.send(ShmEvent::Error(e.to_string())), n);
            }
        }
    }
}

fn spawn_worker<T: Send + 'static>(
    name: String,
    body: impl FnOnce(Sender<Result<(), ShmError>>) -> Result<T, ShmError> + Send + 'static,
) -> Result<JoinHandle<Result<T, ShmError>>, ShmError> {
    let (ready_tx, ready_rx) = crossbeam_channel::bounded(1);
    let handle = std::thread::Builder::new()
        .name(name)
        .spawn(move || body(ready_tx))
        .map_err(|e| ShmError::Thread(format!("spawn failed: {e}")))?;
    match ready_rx.recv() {
        Ok(Ok(())) => Ok(handle),
        Ok(Err(e)) => {
            let _ = handle.join();
            Err(e)
        }
        Err(_) => {
            let _ = handle.join();
            Err(ShmError::Thread("worker died during setup".into()))
        }
    }
}

/// Spawns a thread owning a Node + Subscriber + Listener for `stream` ("excitation",
/// "response", ...), forwarding frames into the bounded `tx`. It returns once the
/// subscriber is registered, or with the setup error. The thread connects to each
/// publisher as soon as it sees it and then sends [`ShmEvent::PublisherAppeared`];
/// from then on delivery is lossless (backpressure). Before that, a publisher can queue
/// at most `subscriber_buffer` frames for it. When `tx` is full, the thread waits, and
/// backpressure propagates to the publisher. The thread stops within about
/// `2 * poll_interval` of `stop` being set or of the receiver being dropped.
pub fn spawn_subscriber(
    opts: &ShmOptions,
    stream: &str,
    tx: Sender<ShmEvent>,
    stop: Arc<AtomicBool>,
) -> Result<JoinHandle<Result<SubscriberStats, ShmError>>, ShmError> {
    opts.validate()?;
    check_stream(stream)?;
    let opts = opts.clone();
    let stream = stream.to_owned();
    spawn_worker(format!("shm-sub-{stream}"), move |ready| {
        subscriber_thread(&opts, &stream, &tx, &stop, ready)
    })
}

fn subscriber_thread(
    opts: &ShmOptions,
    stream: &str,
    tx: &Sender<ShmEvent>,
    stop: &AtomicBool,
    ready: Sender<Result<(), ShmError>>,
) -> Result<SubscriberStats, ShmError> {
    let fail = |e: ShmError| {
        let _ = ready.send(Err(e.clone()));
        Err(e)
    };
    let FrameSubscriber { ports, mut tracker } = match FrameSubscriber::new(opts, stream) {
        Ok(s) => s,
        Err(e) => return fail(e),
    };
    let waitset = match WaitSetBuilder::new()
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
    {
        Ok(w) => w,
        Err(e) => return fail(iox("waitset creation")(e)),
    };
    let _guard = match waitset.attach_notification(&ports.listener) {
        Ok(g) => g,
        Err(e) => return fail(iox("waitset attach")(e)),
    };
    let _ = ready.send(Ok(()));
    drop(ready);

    let mut fwd = Forwarder {
        tx,
        stop,
        poll: opts.poll_interval,
        max_depth: 0,
    };
    let mut present = false;
    let mut last_activity = Instant::now();
    let mut last_cleanup = Instant::now();
    loop {
        if stop.load(Ordering::Acquire) {
            break;
        }
        // Consume notifications first: one that arrives later means new data.
        if let Err(e) = ports.listener.try_wait(|_| {}) {
            tracker.stats.errors += 1;
            if fwd.send(ShmEvent::Error(iox("listener try_wait")(e).to_string())) == Flow::Stop {
                break;
            }
        }
        if !present && ports.publisher_count() > 0 {
            // Connect right away: until a subscriber has connected, a publisher can
            // queue at most `subscriber_buffer` frames for it and discards the rest.
            if let Err(e) = ports.subscriber.update_connections() {
                tracker.stats.errors += 1;
                let msg = iox("subscriber update_connections")(e).to_string();
                if fwd.send(ShmEvent::Error(msg)) == Flow::Stop {
                    break;
                }
            }
            present = true;
            tracker.stats.publisher_appeared += 1;
            if fwd.send(ShmEvent::PublisherAppeared) == Flow::Stop {
                break;
            }
        }
        let (flow, n) = drain(&ports, &mut tracker, &mut fwd, &mut present);
        if flow == Flow::Stop {
            break;
        }
        if n > 0 {
            last_activity = Instant::now();
        }
        if present && ports.publisher_count() == 0 {
            // Deliver what the departed publisher left in our buffer, then report.
            if drain(&ports, &mut tracker, &mut fwd, &mut present).0 == Flow::Stop {
                break;
            }
            present = false;
            tracker.last.clear();
            tracker.stats.publisher_gone += 1;
            if fwd.send(ShmEvent::PublisherGone) == Flow::Stop {
                break;
            }
        } else if present
            && last_activity.elapsed() >= opts.liveness_interval
            && last_cleanup.elapsed() >= opts.liveness_interval
        {
            // Silent stream: a crashed publisher stays registered until its dead node
            // is cleaned up. The count is checked again on the next pass.
            ports.pubsub.try_cleanup_dead_nodes();
            last_cleanup = Instant::now();
        }
        if let Err(e) = waitset.wait_and_process_once_with_timeout(
            |_| CallbackProgression::Continue,
            opts.poll_interval,
        ) {
            tracker.stats.errors += 1;
            let _ = fwd.send(ShmEvent::Error(iox("waitset wait")(e).to_string()));
            tracker.stats.max_queue_depth = fwd.max_depth;
            return Err(iox("waitset wait")(e));
        }
    }
    tracker.stats.max_queue_depth = fwd.max_depth;
    Ok(tracker.stats)
}

/// Spawns a thread owning a Node + Publisher + Notifier for `stream`. It takes frames
/// from `rx`, publishes them, notifies after each batch (whatever is queued, at most
/// `max_batch`), and ends when `rx` is closed and empty. It returns once the publisher
/// exists. A publish error ends the thread with that error (dropping `rx`).
pub fn spawn_publisher(
    opts: &ShmOptions,
    stream: &str,
    rx: Receiver<Frame>,
) -> Result<JoinHandle<Result<PublisherStats, ShmError>>, ShmError> {
    opts.validate()?;
    check_stream(stream)?;
    let opts = opts.clone();
    let stream = stream.to_owned();
    spawn_worker(format!("shm-pub-{stream}"), move |ready| {
        let publisher = match FramePublisher::new(&opts, &stream) {
            Ok(p) => p,
            Err(e) => {
                let _ = ready.send(Err(e.clone()));
                return Err(e);
            }
        };
        let _ = ready.send(Ok(()));
        drop(ready);
        publisher_loop(&publisher, &rx, opts.max_batch)
    })
}

fn publisher_loop(
    publisher: &FramePublisher,
    rx: &Receiver<Frame>,
    max_batch: usize,
) -> Result<PublisherStats, ShmError> {
    let mut stats = PublisherStats::default();
    let publish = |frame: &Frame, stats: &mut PublisherStats| -> Result<(), ShmError> {
        if publisher.publish(frame)? == 0 {
            stats.frames_unsubscribed += 1;
        }
        stats.frames_published += 1;
        Ok(())
    };
    while let Ok(frame) = rx.recv() {
        stats.max_queue_depth = stats.max_queue_depth.max(rx.len() + 1);
        publish(&frame, &mut stats)?;
        for _ in 1..max_batch {
            match rx.try_recv() {
                Ok(frame) => publish(&frame, &mut stats)?,
                Err(_) => break,
            }
        }
        match publisher.notify() {
            Ok(()) => stats.notifications += 1,
            Err(_) => stats.notify_errors += 1,
        }
    }
    stats.backpressure_discards = publisher.backpressure_discards();
    Ok(stats)
}

/// Removes the stale resources of every dead iceoryx2 node under this options'
/// global prefix (all sessions), so that a publisher restarted after a crash gets
/// clean services. Returns the number of nodes cleaned.
pub fn cleanup_dead_nodes(opts: &ShmOptions) -> Result<usize, ShmError> {
    opts.validate()?;
    let config = opts.iceoryx_config()?;
    let mut cleaned = 0;
    Node::<ipc::Service>::list(&config, |state| {
        if let NodeState::Dead(view) = state
            && view.try_remove_stale_resources().is_ok()
        {
            cleaned += 1;
        }
        CallbackProgression::Continue
    })
    .map_err(iox("node list"))?;
    Ok(cleaned)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crossbeam_channel::{RecvTimeoutError, bounded};
    use std::process::Command;

    const CHILD_ENV: &str = "JOINTID_SHM_TEST_CHILD";

    /// Options with a global prefix unique to this process and test, plus a guard.
    /// When the guard drops (keep it alive, declared before any port), it removes the
    /// prefix's persistent 16-byte `*.global_mgmt` segment, which iceoryx2 otherwise
    /// leaves in /dev/shm, one per prefix.
    fn opts(test: &str) -> (ShmOptions, Domain) {
        let o = ShmOptions {
            session: "t".into(),
            global_prefix: Some(format!("jidtest{}_{test}_", std::process::id())),
            ..ShmOptions::default()
        };
        (o.clone(), Domain(o))
    }

    struct Domain(ShmOptions);

    impl Drop for Domain {
        fn drop(&mut self) {
            if let Ok(config) = self.0.iceoryx_config() {
                // SAFETY: the prefix contains this process id and every node of the
                // test is gone by now (the guard is declared first, so it drops last).
                let _ = unsafe {
                    iceoryx2::testing::remove_global_mgmt_segment::<ipc::Service>(&config)
                };
            }
        }
    }

    fn frame(sample: u64, channels: usize) -> Frame {
        Frame {
            sample,
            t_ns: sample * 19_531,
            values: (0..channels)
                .map(|c| sample as f64 + c as f64 * 0.25)
                .collect(),
        }
    }

    /// Next non-error event within `timeout`.
    fn next(rx: &Receiver<ShmEvent>, timeout: Duration) -> Option<ShmEvent> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left) {
                Ok(ShmEvent::Error(e)) => eprintln!("subscriber error: {e}"),
                Ok(ev) => return Some(ev),
                Err(RecvTimeoutError::Timeout | RecvTimeoutError::Disconnected) => return None,
            }
        }
    }

    fn stop_join(
        stop: &AtomicBool,
        handle: JoinHandle<Result<SubscriberStats, ShmError>>,
    ) -> SubscriberStats {
        stop.store(true, Ordering::Release);
        let t0 = Instant::now();
        let stats = handle.join().unwrap().unwrap();
        assert!(
            t0.elapsed() < Duration::from_millis(150),
            "stop took {:?}",
            t0.elapsed()
        );
        stats
    }

    #[test]
    fn lossless_20k_frames_12_channels_threaded() {
        let (o, _domain) = opts("lossless");
        let (ev_tx, ev_rx) = bounded(4096);
        let stop = Arc::new(AtomicBool::new(false));
        let sub = spawn_subscriber(&o, "response", ev_tx, Arc::clone(&stop)).unwrap();
        let (frame_tx, frame_rx) = bounded(4096);
        let publ = spawn_publisher(&o, "response", frame_rx).unwrap();
        // Lossless from the moment the subscriber has connected, which it reports
        // with PublisherAppeared. Before that, only `subscriber_buffer` frames can
        // queue for it.
        assert_eq!(
            next(&ev_rx, Duration::from_secs(5)),
            Some(ShmEvent::PublisherAppeared)
        );

        const N: u64 = 20_000;
        let producer = std::thread::spawn(move || {
            for s in 0..N {
                frame_tx.send(frame(s, 12)).unwrap();
            }
        });
        let t0 = Instant::now();
        let mut expected = 0;
        while expected < N {
            match next(&ev_rx, Duration::from_secs(10)) {
                Some(ShmEvent::Frame(f)) => {
                    assert_eq!(f, frame(expected, 12), "frame out of order or corrupted");
                    expected += 1;
                }
                other => panic!("unexpected {other:?} after {expected} frames"),
            }
        }
        let elapsed = t0.elapsed();
        producer.join().unwrap();
        let pstats = publ.join().unwrap().unwrap();
        assert_eq!(pstats.frames_published, N);
        assert_eq!(pstats.frames_unsubscribed, 0);
        assert_eq!(pstats.backpressure_discards, 0);
        // The publisher is gone now.
        assert_eq!(
            next(&ev_rx, Duration::from_secs(2)),
            Some(ShmEvent::PublisherGone)
        );
        let sstats = stop_join(&stop, sub);
        assert_eq!(sstats.frames_received, N);
        assert_eq!(sstats.drops_detected, 0);
        assert_eq!(sstats.header_mismatches, 0);
        eprintln!("20k frames in {elapsed:?}; publisher {pstats:?}; subscriber {sstats:?}");
    }

    #[test]
    fn header_type_name_and_layout() {
        assert_eq!(std::mem::size_of::<FrameHeader>(), 24);
        assert_eq!(std::mem::align_of::<FrameHeader>(), 8);
        assert_eq!(std::mem::offset_of!(FrameHeader, sample), 0);
        assert_eq!(std::mem::offset_of!(FrameHeader, t_ns), 8);
        assert_eq!(std::mem::offset_of!(FrameHeader, channels), 16);
        assert_eq!(std::mem::offset_of!(FrameHeader, flags), 20);
        assert_eq!(
            unsafe { <FrameHeader as ZeroCopySend>::type_name() },
            FRAME_HEADER_TYPE_NAME
        );
        assert_eq!(
            unsafe { <f64 as ZeroCopySend>::type_name() },
            PAYLOAD_ELEMENT_TYPE_NAME
        );

        // What a live service actually records (and other languages must match).
        let (o, _domain) = opts("typename");
        let publisher = FramePublisher::new(&o, "parameters").unwrap();
        let details = publisher.pubsub.static_config().message_type_details();
        assert_eq!(
            details.user_header.type_name().to_string(),
            FRAME_HEADER_TYPE_NAME
        );
        assert_eq!(details.user_header.size(), 24);
        assert_eq!(details.user_header.alignment(), 8);
        assert_eq!(
            details.payload.type_name().to_string(),
            PAYLOAD_ELEMENT_TYPE_NAME
        );
        assert_eq!(
            details.payload.variant(),
            iceoryx2::service::static_config::message_type_details::TypeVariant::Dynamic
        );
        assert_eq!(details.payload.size(), 8);
        let sc = publisher.pubsub.static_config();
        assert_eq!(sc.subscriber_max_buffer_size(), 8192);
        assert!(!sc.has_safe_overflow());
        assert_eq!(publisher.pubsub.name().as_str(), "t/jointid/parameters");
    }

    #[test]
    fn publisher_gone_and_appeared() {
        let (o, _domain) = opts("gone");
        let (ev_tx, ev_rx) = bounded(1024);
        let stop = Arc::new(AtomicBool::new(false));
        let sub = spawn_subscriber(&o, "excitation", ev_tx, Arc::clone(&stop)).unwrap();
        assert_eq!(next(&ev_rx, Duration::from_millis(200)), None);

        for round in 0..2u64 {
            let publisher = FramePublisher::new(&o, "excitation").unwrap();
            let frames: Vec<Frame> = (0..100).map(|s| frame(round * 1000 + s, 3)).collect();
            assert_eq!(publisher.publish_batch(&frames).unwrap(), 100);
            assert_eq!(
                next(&ev_rx, Duration::from_secs(2)),
                Some(ShmEvent::PublisherAppeared)
            );
            for f in &frames {
                assert_eq!(
                    next(&ev_rx, Duration::from_secs(2)),
                    Some(ShmEvent::Frame(f.clone()))
                );
            }
            assert_eq!(next(&ev_rx, Duration::from_millis(100)), None);
            let t0 = Instant::now();
            drop(publisher);
            assert_eq!(
                next(&ev_rx, Duration::from_secs(2)),
                Some(ShmEvent::PublisherGone)
            );
            assert!(
                t0.elapsed() < Duration::from_millis(200),
                "gone after {:?}",
                t0.elapsed()
            );
        }
        let stats = stop_join(&stop, sub);
        assert_eq!(stats.frames_received, 200);
        assert_eq!(stats.publisher_appeared, 2);
        assert_eq!(stats.publisher_gone, 2);
        assert_eq!(stats.drops_detected, 0);
    }

    #[test]
    fn queued_frames_survive_publisher_drop_once_connected() {
        let (o, _domain) = opts("linger");
        let mut sub = FrameSubscriber::new(&o, "excitation").unwrap();
        let publisher = FramePublisher::new(&o, "excitation").unwrap();
        // The subscriber connects to (and maps) a publisher on its next receive.
        assert_eq!(sub.try_recv().unwrap(), None);
        let frames: Vec<Frame> = (0..500).map(|s| frame(s, 12)).collect();
        assert_eq!(publisher.publish_batch(&frames).unwrap(), 500);
        drop(publisher);
        assert_eq!(sub.publisher_count(), 0);
        for f in &frames {
            assert_eq!(sub.try_recv().unwrap().as_ref(), Some(f));
        }
        assert_eq!(sub.try_recv().unwrap(), None);
    }

    #[test]
    fn sessions_are_isolated() {
        let (a, _domain) = opts("sessions");
        let (c, _domain_c) = opts("sessions2");
        let b = ShmOptions {
            session: "other".into(),
            ..a.clone()
        };
        let mut sub_a = FrameSubscriber::new(&a, "residuals").unwrap();
        let mut sub_b = FrameSubscriber::new(&b, "residuals").unwrap();
        let pub_a = FramePublisher::new(&a, "residuals").unwrap();
        let pub_b = FramePublisher::new(&b, "residuals").unwrap();
        assert_eq!(pub_a.subscriber_count(), 1);
        assert_eq!(pub_b.subscriber_count(), 1);
        assert_eq!(pub_a.publish_batch(&[frame(1, 2), frame(2, 2)]).unwrap(), 2);
        assert_eq!(pub_b.publish_batch(&[frame(7, 5)]).unwrap(), 1);

        assert!(sub_a.wait(Duration::from_secs(1)).unwrap());
        assert_eq!(sub_a.try_recv().unwrap(), Some(frame(1, 2)));
        assert_eq!(sub_a.try_recv().unwrap(), Some(frame(2, 2)));
        assert_eq!(sub_a.try_recv().unwrap(), None);
        assert!(sub_b.wait(Duration::from_secs(1)).unwrap());
        assert_eq!(sub_b.try_recv().unwrap(), Some(frame(7, 5)));
        assert_eq!(sub_b.try_recv().unwrap(), None);
        assert_eq!(sub_a.publisher_count(), 1);

        // A different global prefix is a different world, even with the same session.
        let mut sub_c = FrameSubscriber::new(&c, "residuals").unwrap();
        assert_eq!(sub_c.publisher_count(), 0);
        pub_a.publish_batch(&[frame(3, 2)]).unwrap();
        assert!(!sub_c.wait(Duration::from_millis(100)).unwrap());
        assert_eq!(sub_c.try_recv().unwrap(), None);
        assert_eq!(sub_a.try_recv().unwrap(), Some(frame(3, 2)));
    }

    #[test]
    fn buffer_defaults_absorb_bursts_that_iceoryx_defaults_drop() {
        // iceoryx2's own defaults: buffer 2 with safe overflow -> a burst is overwritten.
        let (base, _domain_iox) = opts("burst_iox");
        let iox_defaults = ShmOptions {
            subscriber_buffer: 2,
            safe_overflow: true,
            ..base
        };
        let mut sub = FrameSubscriber::new(&iox_defaults, "response").unwrap();
        let publisher = FramePublisher::new(&iox_defaults, "response").unwrap();
        let burst: Vec<Frame> = (0..1000).map(|s| frame(s, 12)).collect();
        publisher.publish_batch(&burst).unwrap();
        let mut got = Vec::new();
        while let Some(f) = sub.try_recv().unwrap() {
            got.push(f.sample);
        }
        assert_eq!(got, vec![998, 999], "safe overflow keeps only the newest 2");

        // Ours: a burst of a full buffer (160 ms at 51.2 kHz) with nobody reading
        // arrives complete and in order.
        let (o, _domain) = opts("burst_ours");
        let mut sub = FrameSubscriber::new(&o, "response").unwrap();
        let publisher = FramePublisher::new(&o, "response").unwrap();
        let burst: Vec<Frame> = (0..8192).map(|s| frame(s, 12)).collect();
        assert_eq!(publisher.publish_batch(&burst).unwrap(), 8192);
        for f in &burst {
            assert_eq!(sub.try_recv().unwrap().as_ref(), Some(f));
        }
        assert_eq!(sub.stats().drops_detected, 0);
        assert_eq!(publisher.backpressure_discards(), 0);
        assert!(matches!(
            publisher.publish(&frame(0, 65)),
            Err(ShmError::InvalidFrame(_))
        ));
    }

    #[test]
    fn backpressure_is_lossless_with_a_slow_reader() {
        let (base, _domain) = opts("slowreader");
        // A reader that pauses (20 ms) for less than the timeout loses nothing.
        let o = ShmOptions {
            subscriber_buffer: 16,
            backpressure_timeout: Some(Duration::from_millis(200)),
            ..base
        };
        let (ev_tx, ev_rx) = bounded(8);
        let stop = Arc::new(AtomicBool::new(false));
        let sub = spawn_subscriber(&o, "response", ev_tx, Arc::clone(&stop)).unwrap();
        let (frame_tx, frame_rx) = bounded(64);
        let publ = spawn_publisher(&o, "response", frame_rx).unwrap();
        // PublisherAppeared is sent after the subscriber connected to the publisher.
        assert_eq!(
            next(&ev_rx, Duration::from_secs(2)),
            Some(ShmEvent::PublisherAppeared)
        );
        let producer = std::thread::spawn(move || {
            for s in 0..3000 {
                frame_tx.send(frame(s, 12)).unwrap();
            }
        });
        for s in 0..3000 {
            if s % 500 == 0 {
                std::thread::sleep(Duration::from_millis(20)); // the reader stalls briefly
            }
            assert_eq!(
                next(&ev_rx, Duration::from_secs(2)),
                Some(ShmEvent::Frame(frame(s, 12)))
            );
        }
        producer.join().unwrap();
        let pstats = publ.join().unwrap().unwrap();
        assert_eq!(pstats.backpressure_discards, 0);
        assert_eq!(
            next(&ev_rx, Duration::from_secs(2)),
            Some(ShmEvent::PublisherGone)
        );
        let sstats = stop_join(&stop, sub);
        assert_eq!((sstats.frames_received, sstats.drops_detected), (3000, 0));
    }

    #[test]
    fn stalled_subscriber_cannot_freeze_the_publisher() {
        let (base, _domain) = opts("stalled");
        let o = ShmOptions {
            subscriber_buffer: 16,
            backpressure_timeout: Some(Duration::from_millis(50)),
            ..base
        };
        let mut sub = FrameSubscriber::new(&o, "response").unwrap();
        let publisher = FramePublisher::new(&o, "response").unwrap();
        assert_eq!(sub.try_recv().unwrap(), None); // connects, then stops reading
        let t0 = Instant::now();
        for s in 0..100 {
            publisher.publish(&frame(s, 2)).unwrap();
        }
        let elapsed = t0.elapsed();
        // One 50 ms timeout, then the stalled subscriber is skipped without waiting.
        assert!(elapsed >= Duration::from_millis(50), "{elapsed:?}");
        assert!(elapsed < Duration::from_millis(1000), "{elapsed:?}");
        assert_eq!(publisher.backpressure_discards(), 84);
        for s in 0..16 {
            assert_eq!(sub.try_recv().unwrap(), Some(frame(s, 2)));
        }
        assert_eq!(sub.try_recv().unwrap(), None);
    }

    /// A reader that never reads again is waited for once, however long the session:
    /// while its buffer stays full it stays stalled (the hold is refreshed).
    #[test]
    fn a_hung_subscriber_is_waited_for_once() {
        let (base, _domain) = opts("hung");
        let o = ShmOptions {
            subscriber_buffer: 16,
            backpressure_timeout: Some(Duration::from_millis(20)),
            stall_hold: Duration::from_millis(50),
            ..base
        };
        let mut hung = FrameSubscriber::new(&o, "response").unwrap();
        let publisher = FramePublisher::new(&o, "response").unwrap();
        assert_eq!(hung.try_recv().unwrap(), None); // connects, then never reads again
        let t0 = Instant::now();
        let mut s = 0;
        // Several holds long: 300 ms at one frame per millisecond.
        while t0.elapsed() < Duration::from_millis(300) {
            publisher.publish(&frame(s, 2)).unwrap();
            s += 1;
            std::thread::sleep(Duration::from_millis(1));
        }
        assert_eq!(publisher.stall_events(), 1, "{s} frames");
        assert_eq!(publisher.backpressure_discards(), s - 16);
    }

    #[test]
    fn gaps_are_counted_as_drops() {
        let (o, _domain) = opts("gaps");
        let mut sub = FrameSubscriber::new(&o, "diagnostics").unwrap();
        let publisher = FramePublisher::new(&o, "diagnostics").unwrap();
        publisher
            .publish_batch(&[
                frame(10, 1),
                frame(11, 1),
                frame(15, 1),
                frame(3, 1),
                frame(4, 1),
            ])
            .unwrap();
        let mut got = 0;
        while sub.try_recv().unwrap().is_some() {
            got += 1;
        }
        assert_eq!(got, 5);
        // 12..=14 missing; 15 -> 3 is a restart, not a drop.
        assert_eq!(sub.stats().drops_detected, 3);
    }

    #[test]
    fn invalid_inputs_are_rejected() {
        let (o, _domain) = opts("invalid");
        assert!(matches!(
            FramePublisher::new(&o, "respones"),
            Err(ShmError::UnknownStream(_))
        ));
        let bad = ShmOptions {
            session: "a/b".into(),
            ..o.clone()
        };
        assert!(matches!(bad.validate(), Err(ShmError::InvalidOption(_))));
        let bad = ShmOptions {
            poll_interval: Duration::from_secs(1),
            ..o.clone()
        };
        assert!(matches!(
            spawn_subscriber(&bad, "response", bounded(1).0, Arc::default()),
            Err(ShmError::InvalidOption(_))
        ));
        // Incompatible QoS with an existing service is reported, not ignored.
        let _existing = FramePublisher::new(&o, "response").unwrap();
        let overflow = ShmOptions {
            safe_overflow: true,
            ..o.clone()
        };
        assert!(matches!(
            FrameSubscriber::new(&overflow, "response"),
            Err(ShmError::Iceoryx { .. })
        ));
    }

    /// Child-process half of `crashed_publisher_is_detected_and_replaced`; a no-op
    /// in a normal test run. It publishes, then exits without running destructors.
    #[test]
    fn crash_child_publisher() {
        let Ok(spec) = std::env::var(CHILD_ENV) else {
            return;
        };
        let (prefix, rest) = spec.split_once(':').unwrap();
        let (first, count) = rest.split_once(':').unwrap();
        let (first, count): (u64, u64) = (first.parse().unwrap(), count.parse().unwrap());
        let o = ShmOptions {
            session: "t".into(),
            global_prefix: Some(prefix.into()),
            ..ShmOptions::default()
        };
        let publisher = FramePublisher::new(&o, "response").unwrap();
        let frames: Vec<Frame> = (first..first + count).map(|s| frame(s, 4)).collect();
        publisher.publish_batch(&frames).unwrap();
        std::thread::sleep(Duration::from_millis(300));
        std::process::exit(0); // no Drop: looks like a crash to iceoryx2
    }

    fn run_crashing_child(prefix: &str, first: u64, count: u64) {
        let status = Command::new(std::env::current_exe().unwrap())
            .args(["crash_child_publisher", "--nocapture", "--test-threads=1"])
            .env(CHILD_ENV, format!("{prefix}:{first}:{count}"))
            .status()
            .unwrap();
        assert!(status.success());
    }

    #[test]
    fn crashed_publisher_is_detected_and_replaced() {
        let (o, _domain) = opts("crash");
        let prefix = o.global_prefix.clone().unwrap();

        // 1. A crash with nobody listening leaves a dead node behind; clean it.
        run_crashing_child(&prefix, 0, 10);
        assert_eq!(cleanup_dead_nodes(&o).unwrap(), 1);
        assert_eq!(cleanup_dead_nodes(&o).unwrap(), 0);

        // 2. A crash while subscribed: frames arrive, then PublisherGone via the
        //    subscriber's own dead-node cleanup.
        let (ev_tx, ev_rx) = bounded(1024);
        let stop = Arc::new(AtomicBool::new(false));
        let sub = spawn_subscriber(&o, "response", ev_tx, Arc::clone(&stop)).unwrap();
        run_crashing_child(&prefix, 100, 50);
        assert_eq!(
            next(&ev_rx, Duration::from_secs(2)),
            Some(ShmEvent::PublisherAppeared)
        );
        for s in 100..150 {
            assert_eq!(
                next(&ev_rx, Duration::from_secs(2)),
                Some(ShmEvent::Frame(frame(s, 4)))
            );
        }
        assert_eq!(
            next(&ev_rx, Duration::from_secs(3)),
            Some(ShmEvent::PublisherGone)
        );

        // 3. A restarted publisher (in-process this time) is seen and flows again.
        let publisher = FramePublisher::new(&o, "response").unwrap();
        publisher
            .publish_batch(&[frame(0, 4), frame(1, 4)])
            .unwrap();
        assert_eq!(
            next(&ev_rx, Duration::from_secs(2)),
            Some(ShmEvent::PublisherAppeared)
        );
        assert_eq!(
            next(&ev_rx, Duration::from_secs(2)),
            Some(ShmEvent::Frame(frame(0, 4)))
        );
        assert_eq!(
            next(&ev_rx, Duration::from_secs(2)),
            Some(ShmEvent::Frame(frame(1, 4)))
        );
        let stats = stop_join(&stop, sub);
        assert_eq!(stats.frames_received, 52);
        assert_eq!(stats.drops_detected, 0);
    }

    #[test]
    fn subscriber_stops_when_receiver_dropped() {
        let (o, _domain) = opts("rxdrop");
        let (ev_tx, ev_rx) = bounded(1);
        let sub = spawn_subscriber(&o, "parameters", ev_tx, Arc::default()).unwrap();
        drop(ev_rx);
        let publisher = FramePublisher::new(&o, "parameters").unwrap();
        publisher.publish_batch(&[frame(0, 1)]).unwrap();
        let t0 = Instant::now();
        let stats = sub.join().unwrap().unwrap();
        assert!(t0.elapsed() < Duration::from_millis(200));
        assert!(stats.frames_received <= 1);
    }
}
