//! A simulated booth for host tests of the controller: a clock advanced by hand, projectors
//! whose VSYNC edges come at exact (non-genlocked) rates, a serial line, a host that answers
//! pattern requests after a chosen delay, and a trigger output that records its edges.
//!
//! Time advances from event to event (next VSYNC edge, the controller's alarm, the next host
//! message), so a full 268-frame run takes milliseconds.
#![allow(dead_code)] // each test binary uses a different part of the bench

use std::cell::RefCell;
use std::collections::{BTreeMap, VecDeque};
use std::convert::Infallible;
use std::rc::Rc;

use embedded_hal::digital::{ErrorType, InputPin, OutputPin};
use mlsss_sequencer::{BoardInfo, Controller, MonotonicClock, NoExposureInput};
use mlsss_shared::framing::{ControllerDecoder, HostEncoder, MAX_WIRE_FRAME_LEN};
use mlsss_shared::message::{
    Board, BoundedVec, ControllerMessage, ExhaustedAction, Hello, HostMessage, PatternShown,
    RetryPolicy, SCHEDULE_CHUNK_LEN, ScheduleChunk, ScheduleCommit, ScheduleEntry, ScheduleHeader,
    Triggered,
};
use mlsss_shared::{PROTOCOL_VERSION, SCHEMA_HASH, schedule_checksum};

/// Booth refresh rates of `hardware/booth.toml`, in millihertz.
pub const BOOTH_MHZ: [u64; 4] = [60_000, 59_940, 60_020, 59_970];

/// Shared simulated time.
#[derive(Debug, Default)]
pub struct SimTime {
    pub now_us: u64,
    pub alarm_us: Option<u64>,
    /// Extra time a `wait_until` overshoots by (a busy controller).
    pub wait_overshoot_us: u64,
}

/// The controller's clock in the simulation.
#[derive(Debug, Clone)]
pub struct SimClock(pub Rc<RefCell<SimTime>>);

impl MonotonicClock for SimClock {
    fn now_us(&mut self) -> u64 {
        self.0.borrow().now_us
    }

    fn set_alarm(&mut self, at_us: u64) {
        self.0.borrow_mut().alarm_us = Some(at_us);
    }

    fn wait_until(&mut self, at_us: u64) -> u64 {
        let mut t = self.0.borrow_mut();
        t.now_us = t.now_us.max(at_us) + t.wait_overshoot_us;
        t.now_us
    }
}

/// Bytes in flight on the serial line, with the time each write happened.
#[derive(Debug, Default)]
pub struct Line {
    pub to_controller: VecDeque<u8>,
    pub from_controller: Vec<u8>,
    pub write_times_us: Vec<u64>,
}

/// The controller's end of the serial line.
#[derive(Debug, Clone)]
pub struct SimSerial {
    pub line: Rc<RefCell<Line>>,
    pub time: Rc<RefCell<SimTime>>,
}

impl embedded_io::ErrorType for SimSerial {
    type Error = Infallible;
}

impl embedded_io::Read for SimSerial {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Infallible> {
        let mut line = self.line.borrow_mut();
        let n = buf.len().min(line.to_controller.len());
        for slot in &mut buf[..n] {
            *slot = line.to_controller.pop_front().unwrap_or(0);
        }
        Ok(n)
    }
}

impl embedded_io::ReadReady for SimSerial {
    fn read_ready(&mut self) -> Result<bool, Infallible> {
        Ok(!self.line.borrow().to_controller.is_empty())
    }
}

impl embedded_io::Write for SimSerial {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Infallible> {
        let now = self.time.borrow().now_us;
        let mut line = self.line.borrow_mut();
        line.from_controller.extend_from_slice(buf);
        line.write_times_us.push(now);
        Ok(buf.len())
    }

    fn flush(&mut self) -> Result<(), Infallible> {
        Ok(())
    }
}

/// Edges of an output: (time, level).
pub type EdgeLog = Rc<RefCell<Vec<(u64, bool)>>>;

/// A trigger output that records its edges with their times.
#[derive(Debug, Clone)]
pub struct RecordingPin {
    pub edges: EdgeLog,
    pub time: Rc<RefCell<SimTime>>,
}

impl ErrorType for RecordingPin {
    type Error = Infallible;
}

impl OutputPin for RecordingPin {
    fn set_low(&mut self) -> Result<(), Infallible> {
        let now = self.time.borrow().now_us;
        self.edges.borrow_mut().push((now, false));
        Ok(())
    }

    fn set_high(&mut self) -> Result<(), Infallible> {
        let now = self.time.borrow().now_us;
        self.edges.borrow_mut().push((now, true));
        Ok(())
    }
}

/// A camera exposure-active output: high between the given times.
#[derive(Debug, Clone)]
pub struct CameraActive {
    pub time: Rc<RefCell<SimTime>>,
    /// (from, to) intervals where the input reads high.
    pub high: Rc<RefCell<Vec<(u64, u64)>>>,
}

impl ErrorType for CameraActive {
    type Error = Infallible;
}

impl InputPin for CameraActive {
    fn is_high(&mut self) -> Result<bool, Infallible> {
        let now = self.time.borrow().now_us;
        Ok(self.high.borrow().iter().any(|&(a, b)| a <= now && now < b))
    }

    fn is_low(&mut self) -> Result<bool, Infallible> {
        self.is_high().map(|h| !h)
    }
}

/// A projector's VSYNC generator: edge k at `offset_ns + k * period_ns`.
#[derive(Debug, Clone)]
pub struct Projector {
    pub period_ns: u64,
    pub offset_ns: u64,
    pub next_k: u64,
    /// Edges in [from_us, to_us) are not produced (a projector that lost sync).
    pub missing: Vec<(u64, u64)>,
}

impl Projector {
    pub fn at_millihertz(mhz: u64, offset_ns: u64) -> Self {
        Self {
            period_ns: 1_000_000_000_000 / mhz,
            offset_ns,
            next_k: 0,
            missing: Vec::new(),
        }
    }

    pub fn edge_us(&self, k: u64) -> u64 {
        (self.offset_ns + k * self.period_ns) / 1000
    }
}

/// The default timing of the booth (hardware/booth.toml), with a generous policy.
pub fn booth_header(frame_count: u16) -> ScheduleHeader {
    ScheduleHeader {
        frame_count,
        period_us: 200_000,
        refresh_period_us: 16_667,
        exposure_periods: 2,
        settle_vsyncs: 2,
        trigger_phase_us: 500,
        trigger_width_us: 100,
        ack_timeout_us: 150_000,
        host_silence_timeout_us: 1_000_000,
        policy: RetryPolicy {
            max_retries: 3,
            when_exhausted: ExhaustedAction::Abort,
        },
        projector_exposure: Default::default(),
    }
}

/// `per_projector` frames on each of the 4 projectors in turn (pattern id = frame index).
pub fn booth_entries(per_projector: u16) -> Vec<ScheduleEntry> {
    (0..4u8)
        .flat_map(|p| (0..per_projector).map(move |i| (p, i)))
        .enumerate()
        .map(|(frame, (projector, _))| ScheduleEntry {
            projector,
            pattern: frame as u16,
        })
        .collect()
}

/// How the simulated host answers pattern requests: delay per (frame, attempt), or never.
pub type AckDelay = Box<dyn Fn(u16, u8) -> Option<u64>>;

/// The simulated booth around a controller with trigger output `T` and exposure input `X`.
pub struct Bench<T, X> {
    pub time: Rc<RefCell<SimTime>>,
    pub line: Rc<RefCell<Line>>,
    pub ctl: Option<Controller<SimSerial, T, X, SimClock, 4>>,
    pub projectors: Vec<Projector>,
    pub host_enc: HostEncoder,
    pub host_dec: ControllerDecoder,
    /// Every message from the controller with the time the host received it.
    pub received: Vec<(u64, ControllerMessage)>,
    /// Host messages waiting to be sent: time -> messages.
    pub outgoing: BTreeMap<u64, Vec<HostMessage>>,
    /// Raw bytes waiting to be sent (fault injection): time -> bytes.
    pub outgoing_raw: BTreeMap<u64, Vec<u8>>,
    pub ack_delay: AckDelay,
    /// Host silent (sends nothing, answers nothing) in [from, to).
    pub host_silent: Option<(u64, u64)>,
    /// Send a host Heartbeat this often (0: never).
    pub host_heartbeat_us: u64,
    next_heartbeat_us: u64,
    /// The host sends `Resume` when it sees the run paused.
    pub resume_when_paused: bool,
    pub polls: u64,
    /// `may_sleep()` after each poll: (time, answer).
    pub sleep_log: Vec<(u64, bool)>,
    /// Every host message put on the line: (sequence number, time, message).
    pub sent: Vec<(u16, u64, HostMessage)>,
}

pub const INFO: BoardInfo = BoardInfo {
    board: Board::HostSimulation,
    firmware_version: [0, 1, 0],
    timer_tick_ns: 1000,
};

impl Bench<RecordingPin, NoExposureInput> {
    /// The booth of hardware/booth.toml, a recording trigger output, no exposure input.
    pub fn booth() -> (Self, EdgeLog) {
        let time = Rc::new(RefCell::new(SimTime::default()));
        let edges = Rc::new(RefCell::new(Vec::new()));
        let pin = RecordingPin {
            edges: edges.clone(),
            time: time.clone(),
        };
        (Self::with_pins(time, pin, None), edges)
    }
}

impl<T: OutputPin, X: InputPin> Bench<T, X> {
    pub fn with_pins(time: Rc<RefCell<SimTime>>, trigger: T, exposure: Option<X>) -> Self {
        let line = Rc::new(RefCell::new(Line::default()));
        let serial = SimSerial {
            line: line.clone(),
            time: time.clone(),
        };
        let ctl = Controller::new(serial, trigger, exposure, SimClock(time.clone()), INFO)
            .unwrap_or_else(|e| panic!("controller: {e:?}"));
        // Different phases so the projectors' edges do not coincide.
        let projectors = BOOTH_MHZ
            .iter()
            .zip([1_000_000u64, 5_300_000, 9_700_000, 13_100_000])
            .map(|(&mhz, offset)| Projector::at_millihertz(mhz, offset))
            .collect();
        Self {
            time,
            line,
            ctl: Some(ctl),
            projectors,
            host_enc: HostEncoder::new(),
            host_dec: ControllerDecoder::new(),
            received: Vec::new(),
            outgoing: BTreeMap::new(),
            outgoing_raw: BTreeMap::new(),
            ack_delay: Box::new(|_, _| Some(2_000)),
            host_silent: None,
            host_heartbeat_us: 100_000,
            next_heartbeat_us: 0,
            resume_when_paused: false,
            polls: 0,
            sleep_log: Vec::new(),
            sent: Vec::new(),
        }
    }

    pub fn ctl(&mut self) -> &mut Controller<SimSerial, T, X, SimClock, 4> {
        self.ctl.as_mut().expect("controller present")
    }

    pub fn now(&self) -> u64 {
        self.time.borrow().now_us
    }

    /// Queues a host message to be sent at `at_us`.
    pub fn send_at(&mut self, at_us: u64, message: HostMessage) {
        self.outgoing.entry(at_us).or_default().push(message);
    }

    /// Queues a host message to be sent now.
    pub fn send(&mut self, message: HostMessage) {
        let now = self.now();
        self.send_at(now, message);
    }

    /// Hello, upload, arm and start, each sent now (the controller handles them in order).
    pub fn start_run(&mut self, header: ScheduleHeader, entries: &[ScheduleEntry]) {
        self.send(hello());
        self.upload(header, entries);
        self.send(HostMessage::Arm);
        self.send(HostMessage::Start);
    }

    pub fn upload(&mut self, header: ScheduleHeader, entries: &[ScheduleEntry]) {
        self.send(HostMessage::ScheduleBegin(header));
        for (i, chunk) in entries.chunks(SCHEDULE_CHUNK_LEN).enumerate() {
            self.send(HostMessage::ScheduleChunk(ScheduleChunk {
                first_frame: (i * SCHEDULE_CHUNK_LEN) as u16,
                entries: BoundedVec::from_slice(chunk).expect("chunk fits"),
            }));
        }
        self.send(HostMessage::ScheduleCommit(ScheduleCommit {
            frame_count: entries.len() as u16,
            checksum: schedule_checksum(entries),
        }));
    }

    fn host_is_silent(&self, t: u64) -> bool {
        self.host_silent.is_some_and(|(a, b)| a <= t && t < b)
    }

    /// Runs the booth until `end_us` or until the controller reports `Done` (plus a little so
    /// the final reports arrive).
    pub fn run_until(&mut self, end_us: u64) {
        let mut done_at: Option<u64> = None;
        loop {
            let now = self.now();
            let alarm = self.time.borrow().alarm_us.unwrap_or(u64::MAX).max(now + 1);
            let next_edge = self
                .projectors
                .iter()
                .map(|p| p.edge_us(p.next_k))
                .min()
                .unwrap_or(u64::MAX);
            let next_send = self
                .outgoing
                .keys()
                .next()
                .copied()
                .into_iter()
                .chain(self.outgoing_raw.keys().next().copied())
                .chain((self.host_heartbeat_us > 0).then_some(self.next_heartbeat_us))
                .min()
                .unwrap_or(u64::MAX)
                .max(now);
            // A board polls continuously: unread bytes are handled without waiting.
            let pending_input = !self.line.borrow().to_controller.is_empty();
            let t = if pending_input {
                now
            } else {
                alarm.min(next_edge).min(next_send)
            };
            let stop = done_at.map_or(end_us, |d| d + 50_000).min(end_us);
            if t > stop {
                break;
            }
            self.time.borrow_mut().now_us = t;
            self.deliver_edges(t);
            self.deliver_host_bytes(t);
            self.polls += 1;
            self.ctl().poll().unwrap_or_else(|e| panic!("poll: {e:?}"));
            // A poll may have waited for a trigger edge: log at the time it ended.
            let may_sleep = self.ctl().may_sleep();
            let after = self.now();
            self.sleep_log.push((after, may_sleep));
            self.collect(t);
            if done_at.is_none()
                && self
                    .received
                    .iter()
                    .any(|(_, m)| matches!(m, ControllerMessage::Done(_)))
            {
                done_at = Some(t);
            }
        }
    }

    fn deliver_edges(&mut self, t: u64) {
        while let Some((i, edge)) = self
            .projectors
            .iter()
            .enumerate()
            .map(|(i, p)| (i, p.edge_us(p.next_k)))
            .filter(|&(_, e)| e <= t)
            .min_by_key(|&(_, e)| e)
        {
            let p = &mut self.projectors[i];
            p.next_k += 1;
            if p.missing.iter().any(|&(a, b)| a <= edge && edge < b) {
                continue;
            }
            self.ctl().on_vsync(i as u8, edge);
        }
    }

    fn deliver_host_bytes(&mut self, t: u64) {
        if self.host_heartbeat_us > 0 && t >= self.next_heartbeat_us {
            self.next_heartbeat_us = t + self.host_heartbeat_us;
            if !self.host_is_silent(t) {
                self.send_at(
                    t,
                    HostMessage::Heartbeat(mlsss_shared::message::HostHeartbeat {
                        host_time_us: t,
                    }),
                );
            }
        }
        let due: Vec<u64> = self.outgoing.range(..=t).map(|(&k, _)| k).collect();
        for k in due {
            for message in self.outgoing.remove(&k).unwrap_or_default() {
                if self.host_is_silent(t) {
                    continue;
                }
                let mut buf = [0u8; MAX_WIRE_FRAME_LEN];
                let (seq, bytes) = self.host_enc.encode(&message, &mut buf).expect("encode");
                self.sent.push((seq, t, message.clone()));
                self.line
                    .borrow_mut()
                    .to_controller
                    .extend(bytes.iter().copied());
            }
        }
        let due: Vec<u64> = self.outgoing_raw.range(..=t).map(|(&k, _)| k).collect();
        for k in due {
            let bytes = self.outgoing_raw.remove(&k).unwrap_or_default();
            self.line.borrow_mut().to_controller.extend(bytes);
        }
    }

    /// Decodes what the controller sent and lets the host react.
    fn collect(&mut self, t: u64) {
        let bytes = std::mem::take(&mut self.line.borrow_mut().from_controller);
        let mut messages = Vec::new();
        for frame in self.host_dec.feed(&bytes) {
            messages.push(frame.expect("controller frames are valid").message);
        }
        for message in messages {
            match &message {
                ControllerMessage::PatternRequest(r) if !self.host_is_silent(t) => {
                    if let Some(delay) = (self.ack_delay)(r.frame, r.attempt) {
                        let shown = HostMessage::PatternShown(PatternShown {
                            frame: r.frame,
                            attempt: r.attempt,
                            pattern: r.pattern,
                        });
                        self.send_at(t + delay, shown);
                    }
                }
                ControllerMessage::Status(s)
                    if self.resume_when_paused
                        && s.state == mlsss_shared::message::ControllerState::Paused =>
                {
                    self.send_at(t + 1_000, HostMessage::Resume);
                }
                _ => {}
            }
            self.received.push((t, message));
        }
    }

    /// Every `Triggered` report, in order.
    pub fn triggers(&self) -> Vec<Triggered> {
        self.received
            .iter()
            .filter_map(|(_, m)| match m {
                ControllerMessage::Triggered(t) => Some(*t),
                _ => None,
            })
            .collect()
    }

    /// Messages matching `f`.
    pub fn find<R>(&self, f: impl Fn(&ControllerMessage) -> Option<R>) -> Vec<R> {
        self.received.iter().filter_map(|(_, m)| f(m)).collect()
    }

    /// Edge `count` (1-based, as the controller counts after Arm) of projector `p`, given the
    /// edge index the controller saw first after arming.
    pub fn edge_time_us(&self, p: usize, k: u64) -> u64 {
        self.projectors[p].edge_us(k)
    }
}

pub fn hello() -> HostMessage {
    HostMessage::Hello(Hello {
        protocol_version: PROTOCOL_VERSION,
        schema_hash: SCHEMA_HASH,
    })
}
