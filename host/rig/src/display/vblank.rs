//! Waiting for the display's vertical blank after a frame has been put on screen, through the X
//! Present extension (`PresentNotifyMSC`): the server answers at the next vblank of the window's
//! CRTC with that vblank's counter (MSC). A frame written to the visible buffer before vblank N is
//! scanned out whole from the refresh after N, so acknowledging after N keeps "shown" in step
//! with the refresh. The controller then waits its settle count of VSYNCs (DESIGN section 7).
//!
//! A separate connection is used (softbuffer owns winit's); the frame's pixels are already on
//! screen when this is asked (see `windows`), so the order between connections does not matter.

use std::collections::HashSet;
use std::time::{Duration, Instant};

use x11rb::connection::{Connection, RequestConnection};
use x11rb::protocol::Event;
use x11rb::protocol::present::{self, CompleteKind, ConnectionExt as _, EventMask};
use x11rb::rust_connection::RustConnection;

use crate::RigError;

/// One vertical blank.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Vblank {
    /// The CRTC's frame counter at that vblank.
    pub msc: u64,
    /// Its time, microseconds on the server's clock.
    pub ust: u64,
}

/// Waits for vblanks of windows of the display `DISPLAY` names.
pub struct VblankWaiter {
    conn: RustConnection,
    selected: HashSet<u32>,
    serial: u32,
}

fn x_error(what: &str, e: impl std::fmt::Display) -> RigError {
    RigError::Display(format!("{what}: {e}"))
}

impl VblankWaiter {
    /// Connects; `None` when the server has no Present extension (then "shown" is acknowledged
    /// once the frame is on screen, not aligned to a vblank).
    pub fn connect() -> Result<Option<Self>, RigError> {
        let (conn, _) =
            RustConnection::connect(None).map_err(|e| x_error("connecting for vblanks", e))?;
        let has_present = conn
            .extension_information(present::X11_EXTENSION_NAME)
            .map_err(|e| x_error("querying the Present extension", e))?
            .is_some();
        if !has_present {
            return Ok(None);
        }
        conn.present_query_version(1, 0)
            .map_err(|e| x_error("Present version", e))?
            .reply()
            .map_err(|e| x_error("Present version", e))?;
        Ok(Some(Self {
            conn,
            selected: HashSet::new(),
            serial: 0,
        }))
    }

    /// Blocks until the next vblank of the CRTC showing `window` (at most `timeout`).
    pub fn next_vblank(&mut self, window: u32, timeout: Duration) -> Result<Vblank, RigError> {
        self.select_complete_events(window)?;
        self.serial = self.serial.wrapping_add(1);
        // target 0 with divisor 1: the first MSC after now, i.e. the next vblank.
        self.conn
            .present_notify_msc(window, self.serial, 0, 1, 0)
            .map_err(|e| x_error("PresentNotifyMSC", e))?;
        self.conn.flush().map_err(|e| x_error("flushing", e))?;
        let deadline = Instant::now() + timeout;
        loop {
            let event = self
                .conn
                .poll_for_event()
                .map_err(|e| x_error("reading X events", e))?;
            match event {
                Some(Event::PresentCompleteNotify(e))
                    if e.kind == CompleteKind::NOTIFY_MSC && e.serial == self.serial =>
                {
                    return Ok(Vblank {
                        msc: e.msc,
                        ust: e.ust,
                    });
                }
                Some(_) => {}
                None if Instant::now() >= deadline => {
                    return Err(RigError::Display(format!(
                        "no vertical blank within {timeout:?}: is the monitor on (not in DPMS \
                         standby)?"
                    )));
                }
                None => std::thread::sleep(Duration::from_micros(500)),
            }
        }
    }

    fn select_complete_events(&mut self, window: u32) -> Result<(), RigError> {
        if self.selected.contains(&window) {
            return Ok(());
        }
        let eid = self
            .conn
            .generate_id()
            .map_err(|e| x_error("allocating an event id", e))?;
        self.conn
            .present_select_input(eid, window, EventMask::COMPLETE_NOTIFY)
            .map_err(|e| x_error("PresentSelectInput", e))?;
        self.selected.insert(window);
        Ok(())
    }
}
