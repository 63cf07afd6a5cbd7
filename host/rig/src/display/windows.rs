//! The projector windows: a winit event loop on its own thread owns one borderless fullscreen
//! window per projector, drawn with softbuffer (CPU pixels put straight into the window: no GPU
//! scaling, no colour management). The run loop talks to it through commands and waits for each
//! "presented" answer, so the controller hears "shown" only after the frame has been presented.
//!
//! X11 only: an X session lets a program place a window on a given monitor, which a booth needs
//! (Wayland compositors decide placement themselves). winit allows one event loop per process, so
//! a process opens [`ProjectorWindows`] (or calls [`list_monitors`]) once.

use std::collections::BTreeMap;
use std::num::NonZeroU32;
use std::sync::Arc;
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender};
use std::thread::{self, JoinHandle};
use std::time::Duration;

use softbuffer::{Context, Surface};
use winit::application::ApplicationHandler;
use winit::dpi::{PhysicalPosition, PhysicalSize};
use winit::event::{ElementState, WindowEvent};
use winit::event_loop::{ActiveEventLoop, EventLoop, EventLoopProxy, OwnedDisplayHandle};
use winit::monitor::MonitorHandle;
use winit::platform::x11::EventLoopBuilderExtX11;
use winit::window::{Fullscreen, Window, WindowId};

use super::raster::rasterise;
use super::vblank::{Vblank, VblankWaiter};
use super::{MonitorInfo, find_monitor, number_monitors};
use crate::RigError;
use crate::backend::ProjectorBackend;
use mlsss_core::capture::Pattern;

/// How long opening the windows may take before the display server is deemed unresponsive.
const OPEN_TIMEOUT: Duration = Duration::from_secs(20);
/// How long one present may take.
const PRESENT_TIMEOUT: Duration = Duration::from_secs(5);
/// How long to wait for the vblank after a present (a 60 Hz display has one every 17 ms; the
/// margin is for a loaded machine).
const VBLANK_TIMEOUT: Duration = Duration::from_secs(2);

/// One projector window to open.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WindowSpec {
    /// The projector.
    pub projector: u8,
    /// The monitor it is plugged into (index as numbered by [`super::number_monitors`]).
    pub monitor: usize,
    /// The projector's native resolution: patterns are drawn at this size, one window pixel per
    /// projector pixel, from the monitor's top-left corner.
    pub width: u32,
    /// See `width`.
    pub height: u32,
}

/// A frame that has been presented.
#[derive(Debug, Clone, PartialEq)]
pub struct Presented {
    /// The projector.
    pub projector: u8,
    /// The monitor it showed on.
    pub monitor: MonitorInfo,
    /// The window's size when it was drawn (the monitor's mode when fullscreen worked).
    pub window_width: u32,
    /// See `window_width`.
    pub window_height: u32,
    /// The vertical blank after which the frame is scanned out whole; `None` when the X server
    /// has no Present extension (then not aligned to the refresh).
    pub vblank: Option<Vblank>,
}

enum Command {
    Show {
        projector: u8,
        pattern: Pattern,
        reply: Sender<Result<Presented, RigError>>,
    },
    Quit,
}

/// The monitors of the display server (`DISPLAY`), numbered left to right then top to bottom.
pub fn list_monitors() -> Result<Vec<MonitorInfo>, RigError> {
    let windows = ProjectorWindows::open(&[])?;
    Ok(windows.monitors().to_vec())
}

/// Projector windows on real monitors.
pub struct ProjectorWindows {
    proxy: EventLoopProxy<Command>,
    thread: Option<JoinHandle<()>>,
    monitors: Vec<MonitorInfo>,
    keys: Receiver<()>,
}

impl ProjectorWindows {
    /// Opens one window per spec, each black, and returns once every window is mapped; an error
    /// if there is no display server or a spec names a monitor that does not exist.
    pub fn open(specs: &[WindowSpec]) -> Result<Self, RigError> {
        let (ready_tx, ready_rx) = mpsc::channel();
        let (key_tx, keys) = mpsc::channel();
        let specs = specs.to_vec();
        let thread = thread::Builder::new()
            .name("projector-windows".into())
            .spawn(move || run_window_thread(specs, ready_tx, key_tx))
            .map_err(|e| RigError::Display(format!("starting the window thread: {e}")))?;
        let ready = ready_rx.recv_timeout(OPEN_TIMEOUT);
        let (proxy, monitors) = match ready {
            Ok(Ok(opened)) => opened,
            Ok(Err(e)) => {
                let _ = thread.join();
                return Err(e);
            }
            Err(_) => {
                return Err(RigError::Display(
                    "the display server did not map the projector windows in time".into(),
                ));
            }
        };
        Ok(Self {
            proxy,
            thread: Some(thread),
            monitors,
            keys,
        })
    }

    /// The display server's monitors.
    pub fn monitors(&self) -> &[MonitorInfo] {
        &self.monitors
    }

    /// Shows `pattern` on `projector`'s window and black on the others; returns once the frame
    /// has been presented and the display server has processed it.
    pub fn present(&mut self, projector: u8, pattern: &Pattern) -> Result<Presented, RigError> {
        let (reply, answer) = mpsc::channel();
        self.proxy
            .send_event(Command::Show {
                projector,
                pattern: *pattern,
                reply,
            })
            .map_err(|_| RigError::Display("the projector windows were closed".into()))?;
        match answer.recv_timeout(PRESENT_TIMEOUT) {
            Ok(presented) => presented,
            Err(RecvTimeoutError::Timeout) => Err(RigError::Display(format!(
                "projector {projector}: no frame presented within {PRESENT_TIMEOUT:?}"
            ))),
            Err(RecvTimeoutError::Disconnected) => Err(RigError::Display(
                "the projector windows were closed".into(),
            )),
        }
    }

    /// Waits until a key is pressed in a projector window (or one is closed), at most `timeout`
    /// (`None`: forever); whether one was.
    pub fn wait_for_key(&self, timeout: Option<Duration>) -> bool {
        match timeout {
            Some(t) => self.keys.recv_timeout(t).is_ok(),
            None => self.keys.recv().is_ok(),
        }
    }
}

impl ProjectorBackend for ProjectorWindows {
    fn show(&mut self, projector: u8, pattern: &Pattern) -> Result<(), RigError> {
        self.present(projector, pattern).map(|_| ())
    }
}

impl Drop for ProjectorWindows {
    fn drop(&mut self) {
        if self.proxy.send_event(Command::Quit).is_ok()
            && let Some(thread) = self.thread.take()
        {
            let _ = thread.join();
        }
    }
}

type Opened = (EventLoopProxy<Command>, Vec<MonitorInfo>);

fn run_window_thread(
    specs: Vec<WindowSpec>,
    ready: Sender<Result<Opened, RigError>>,
    keys: Sender<()>,
) {
    let event_loop = match EventLoop::<Command>::with_user_event()
        .with_x11()
        .with_any_thread(true)
        .build()
    {
        Ok(event_loop) => event_loop,
        Err(winit::error::EventLoopError::RecreationAttempt) => {
            let _ = ready.send(Err(RigError::Display(
                "the projector windows can be opened once per process (winit's event loop)".into(),
            )));
            return;
        }
        Err(e) => {
            let _ = ready.send(Err(RigError::Display(format!(
                "cannot open the X display (is DISPLAY set and an X server running?): {e}"
            ))));
            return;
        }
    };
    let mut app = WindowApp {
        specs,
        proxy: Some(event_loop.create_proxy()),
        ready: Some(ready),
        keys,
        context: None,
        monitors: vec![],
        windows: BTreeMap::new(),
        vblank: None,
    };
    if let Err(e) = event_loop.run_app(&mut app) {
        app.fail(RigError::Display(format!(
            "the window event loop failed: {e}"
        )));
    }
}

/// One open projector window and what it shows.
struct ProjectorWindow {
    spec: WindowSpec,
    monitor: MonitorInfo,
    window: Arc<Window>,
    surface: Surface<OwnedDisplayHandle, Arc<Window>>,
    /// What the window shows (black until told otherwise).
    content: Pattern,
    /// Whether the display server has exposed (mapped) the window: drawing before that is lost.
    exposed: bool,
}

impl ProjectorWindow {
    /// Draws `content`, presents it, and waits until the X server has processed the frame.
    fn draw(&mut self) -> Result<(u32, u32), RigError> {
        let PhysicalSize { width, height } = self.window.inner_size();
        let (Some(w), Some(h)) = (NonZeroU32::new(width), NonZeroU32::new(height)) else {
            return Err(RigError::Display(format!(
                "projector {}: the window has no area",
                self.spec.projector
            )));
        };
        let failed = |what: &str, e: softbuffer::SoftBufferError| {
            RigError::Display(format!("projector {}: {what}: {e}", self.spec.projector))
        };
        self.surface
            .resize(w, h)
            .map_err(|e| failed("resizing the frame", e))?;
        let mut buffer = self
            .surface
            .buffer_mut()
            .map_err(|e| failed("getting the frame", e))?;
        rasterise(
            &self.content,
            (self.spec.width, self.spec.height),
            (width, height),
            &mut buffer,
        );
        buffer
            .present()
            .map_err(|e| failed("presenting the frame", e))?;
        // softbuffer and winit share one X connection and the server handles a connection's
        // requests in order, so the reply to this round trip (TranslateCoordinates) arrives only
        // after the server has put the frame's pixels on screen.
        let _ = self.window.inner_position();
        Ok((width, height))
    }

    /// The X window id (for the Present extension).
    fn x_window(&self) -> Option<u32> {
        use raw_window_handle::{HasWindowHandle, RawWindowHandle};
        match self.window.window_handle().ok()?.as_raw() {
            RawWindowHandle::Xlib(h) => u32::try_from(h.window).ok(),
            RawWindowHandle::Xcb(h) => Some(h.window.get()),
            _ => None,
        }
    }
}

struct WindowApp {
    specs: Vec<WindowSpec>,
    proxy: Option<EventLoopProxy<Command>>,
    /// Taken when the open finishes, well or not.
    ready: Option<Sender<Result<Opened, RigError>>>,
    keys: Sender<()>,
    context: Option<Context<OwnedDisplayHandle>>,
    monitors: Vec<MonitorInfo>,
    windows: BTreeMap<u8, ProjectorWindow>,
    vblank: Option<VblankWaiter>,
}

impl WindowApp {
    fn fail(&mut self, error: RigError) {
        if let Some(ready) = self.ready.take() {
            let _ = ready.send(Err(error));
        }
    }

    fn open_windows(&mut self, event_loop: &ActiveEventLoop) -> Result<(), RigError> {
        let handles: Vec<(MonitorInfo, MonitorHandle)> = event_loop
            .available_monitors()
            .map(|handle| (monitor_info(&handle), handle))
            .collect();
        self.monitors = number_monitors(handles.iter().map(|(info, _)| info.clone()).collect());
        let display = event_loop.owned_display_handle();
        let context = Context::new(display)
            .map_err(|e| RigError::Display(format!("softbuffer context: {e}")))?;
        for spec in self.specs.clone() {
            let monitor = find_monitor(&self.monitors, spec.monitor, spec.projector)?.clone();
            let handle = handles
                .iter()
                .find(|(info, _)| info.name == monitor.name && info.x == monitor.x)
                .map(|(_, h)| h.clone());
            let window = create_window(event_loop, &spec, &monitor, handle)?;
            let surface = Surface::new(&context, window.clone())
                .map_err(|e| RigError::Display(format!("softbuffer surface: {e}")))?;
            self.windows.insert(
                spec.projector,
                ProjectorWindow {
                    spec,
                    monitor,
                    window,
                    surface,
                    content: Pattern::Black,
                    exposed: false,
                },
            );
        }
        self.context = Some(context);
        self.vblank = VblankWaiter::connect()?;
        Ok(())
    }

    /// Reports the open as done once every window has been exposed and drawn.
    fn report_ready_when_all_exposed(&mut self) {
        if self.windows.values().all(|w| w.exposed)
            && let (Some(ready), Some(proxy)) = (self.ready.take(), self.proxy.take())
        {
            let _ = ready.send(Ok((proxy, self.monitors.clone())));
        }
    }

    fn show(&mut self, projector: u8, pattern: Pattern) -> Result<Presented, RigError> {
        if !self.windows.contains_key(&projector) {
            return Err(RigError::Display(format!(
                "projector {projector} has no window (opened: {:?})",
                self.windows.keys().collect::<Vec<_>>()
            )));
        }
        // Dark projectors first, so the lit one never shares the scene with a stale pattern.
        for (k, window) in &mut self.windows {
            if *k != projector && window.content != Pattern::Black {
                window.content = Pattern::Black;
                window.draw()?;
            }
        }
        let window = self
            .windows
            .get_mut(&projector)
            .ok_or_else(|| RigError::Display(format!("projector {projector} has no window")))?;
        window.content = pattern;
        let (window_width, window_height) = window.draw()?;
        let vblank = match (&mut self.vblank, window.x_window()) {
            (Some(waiter), Some(id)) => Some(waiter.next_vblank(id, VBLANK_TIMEOUT)?),
            _ => None,
        };
        Ok(Presented {
            projector,
            monitor: window.monitor.clone(),
            window_width,
            window_height,
            vblank,
        })
    }
}

impl ApplicationHandler<Command> for WindowApp {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.context.is_some() || self.ready.is_none() {
            return;
        }
        if let Err(e) = self.open_windows(event_loop) {
            self.fail(e);
            event_loop.exit();
            return;
        }
        self.report_ready_when_all_exposed();
    }

    fn user_event(&mut self, event_loop: &ActiveEventLoop, command: Command) {
        match command {
            Command::Show {
                projector,
                pattern,
                reply,
            } => {
                let _ = reply.send(self.show(projector, pattern));
            }
            Command::Quit => event_loop.exit(),
        }
    }

    fn window_event(&mut self, _: &ActiveEventLoop, id: WindowId, event: WindowEvent) {
        let Some(window) = self.windows.values_mut().find(|w| w.window.id() == id) else {
            return;
        };
        match event {
            WindowEvent::RedrawRequested | WindowEvent::Resized(_) => {
                // An expose (mapping, or uncovering) or a new size: draw what the window shows.
                match window.draw() {
                    Ok(_) => {
                        window.exposed = true;
                        self.report_ready_when_all_exposed();
                    }
                    Err(e) => self.fail(e),
                }
            }
            WindowEvent::KeyboardInput { event, .. } if event.state == ElementState::Pressed => {
                let _ = self.keys.send(());
            }
            WindowEvent::CloseRequested => {
                let _ = self.keys.send(());
            }
            _ => {}
        }
    }
}

fn monitor_info(handle: &MonitorHandle) -> MonitorInfo {
    let PhysicalPosition { x, y } = handle.position();
    let PhysicalSize { width, height } = handle.size();
    MonitorInfo {
        index: 0,
        name: handle.name().unwrap_or_else(|| "unnamed".into()),
        x,
        y,
        width,
        height,
        refresh_hz: handle
            .refresh_rate_millihertz()
            .map(|mhz| f64::from(mhz) / 1000.0),
    }
}

/// A borderless window covering `monitor`: placed and sized explicitly (which is all there is
/// without a window manager) and asked to be fullscreen (which a window manager honours by
/// removing panels and, in compositing managers, unredirecting the window).
fn create_window(
    event_loop: &ActiveEventLoop,
    spec: &WindowSpec,
    monitor: &MonitorInfo,
    handle: Option<MonitorHandle>,
) -> Result<Arc<Window>, RigError> {
    let attributes = Window::default_attributes()
        .with_title(format!("mlsss projector {}", spec.projector))
        .with_decorations(false)
        .with_resizable(false)
        .with_position(PhysicalPosition::new(monitor.x, monitor.y))
        .with_inner_size(PhysicalSize::new(monitor.width, monitor.height))
        .with_fullscreen(Some(Fullscreen::Borderless(handle)));
    let window = event_loop.create_window(attributes).map_err(|e| {
        RigError::Display(format!(
            "opening the window of projector {} on monitor {}: {e}",
            spec.projector, monitor.index
        ))
    })?;
    window.set_cursor_visible(false);
    Ok(Arc::new(window))
}
