//! Projector output on real displays (DESIGN section 7): one borderless fullscreen window per
//! projector on the monitor the booth maps it to, the pattern drawn pixel-exact at the projector's
//! native resolution, and "shown" reported only once the frame has reached the display server.
//!
//! - [`raster`]: a pattern as 8-bit window pixels.
//! - [`vblank`]: waiting for the next vertical blank (X Present extension).
//! - [`windows`]: the window thread (winit + softbuffer, X11) and the [`ProjectorWindows`] backend.
//!
//! Monitors are numbered left to right, then top to bottom (by their position on the virtual
//! screen), so "monitor K" names the same connector as long as the desktop layout is unchanged.

pub mod raster;
pub mod vblank;
pub mod windows;

use serde::Serialize;

use crate::RigError;
use mlsss_core::booth::Booth;

pub use windows::{ProjectorWindows, WindowSpec, list_monitors};

/// One monitor of the display server.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MonitorInfo {
    /// Index used by `--monitor` and the booth's `monitor` field.
    pub index: usize,
    /// The connector name (e.g. `HDMI-1`), if the server reports one.
    pub name: String,
    /// Top-left corner on the virtual screen, physical pixels.
    pub x: i32,
    /// Top-left corner on the virtual screen, physical pixels.
    pub y: i32,
    /// Current mode, physical pixels.
    pub width: u32,
    /// Current mode, physical pixels.
    pub height: u32,
    /// Refresh rate of the current mode, if the server reports one.
    pub refresh_hz: Option<f64>,
}

impl MonitorInfo {
    /// `0 "HDMI-1" 1024x768+0+0 @ 60.00 Hz`, for messages.
    pub fn describe(&self) -> String {
        let refresh = self
            .refresh_hz
            .map(|hz| format!(" @ {hz:.2} Hz"))
            .unwrap_or_default();
        format!(
            "{} \"{}\" {}x{}{:+}{:+}{refresh}",
            self.index, self.name, self.width, self.height, self.x, self.y
        )
    }
}

/// The monitor projector `k` is plugged into: the booth's `monitor` field, else monitor `k`.
pub fn projector_monitor(booth: &Booth, k: u8) -> usize {
    booth
        .projectors
        .get(usize::from(k))
        .and_then(|p| p.monitor)
        .map_or(usize::from(k), |m| m as usize)
}

/// The window of projector `k` (on `monitor`, else where the booth maps it).
pub fn window_spec(booth: &Booth, k: u8, monitor: Option<usize>) -> Result<WindowSpec, RigError> {
    let projector = booth.projectors.get(usize::from(k)).ok_or_else(|| {
        RigError::Display(format!(
            "the booth has no projector {k} (it has {})",
            booth.projectors.len()
        ))
    })?;
    Ok(WindowSpec {
        projector: k,
        monitor: monitor.unwrap_or_else(|| projector_monitor(booth, k)),
        width: projector.width,
        height: projector.height,
    })
}

/// An error unless `monitor`'s mode is the projector's native resolution: otherwise the
/// projector rescales the picture and no projector pixel shows exactly one pattern pixel.
pub fn check_native_mode(monitor: &MonitorInfo, spec: &WindowSpec) -> Result<(), RigError> {
    if (monitor.width, monitor.height) == (spec.width, spec.height) {
        return Ok(());
    }
    Err(RigError::Display(format!(
        "projector {} is {}x{} but its monitor {} runs at {}x{}: set the output's mode to the \
         projector's native resolution (xrandr --output {} --mode {}x{})",
        spec.projector,
        spec.width,
        spec.height,
        monitor.describe(),
        monitor.width,
        monitor.height,
        monitor.name,
        spec.width,
        spec.height
    )))
}

/// Sorts monitors by position (left to right, then top to bottom) and numbers them.
pub fn number_monitors(mut monitors: Vec<MonitorInfo>) -> Vec<MonitorInfo> {
    monitors.sort_by(|a, b| (a.x, a.y, &a.name).cmp(&(b.x, b.y, &b.name)));
    for (index, m) in monitors.iter_mut().enumerate() {
        m.index = index;
    }
    monitors
}

/// The monitor `index`, or an error naming the monitors that exist.
pub fn find_monitor(
    monitors: &[MonitorInfo],
    index: usize,
    projector: u8,
) -> Result<&MonitorInfo, RigError> {
    monitors.get(index).ok_or_else(|| RigError::MissingMonitor {
        projector,
        monitor: index,
        available: describe_all(monitors),
    })
}

/// Every monitor on one line, for messages.
pub fn describe_all(monitors: &[MonitorInfo]) -> String {
    if monitors.is_empty() {
        return "none".into();
    }
    monitors
        .iter()
        .map(MonitorInfo::describe)
        .collect::<Vec<_>>()
        .join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn monitor(name: &str, x: i32, y: i32) -> MonitorInfo {
        MonitorInfo {
            index: 99,
            name: name.into(),
            x,
            y,
            width: 1024,
            height: 768,
            refresh_hz: Some(60.0),
        }
    }

    #[test]
    fn monitors_are_numbered_left_to_right_then_top_to_bottom() {
        let numbered = number_monitors(vec![
            monitor("DP-2", 1024, 0),
            monitor("HDMI-1", 0, 768),
            monitor("DP-1", 0, 0),
        ]);
        let names: Vec<_> = numbered.iter().map(|m| m.name.as_str()).collect();
        assert_eq!(names, ["DP-1", "HDMI-1", "DP-2"]);
        assert_eq!(
            numbered.iter().map(|m| m.index).collect::<Vec<_>>(),
            [0, 1, 2]
        );
    }

    #[test]
    fn projector_k_is_on_monitor_k_unless_the_booth_says_otherwise() {
        let mut booth = Booth::builtin(true);
        assert_eq!(projector_monitor(&booth, 2), 2);
        booth.projectors[2].monitor = Some(0);
        assert_eq!(projector_monitor(&booth, 2), 0);
        let spec = window_spec(&booth, 2, Some(5)).unwrap();
        assert_eq!(spec.monitor, 5);
        assert_eq!((spec.width, spec.height), (256, 192));
        assert!(window_spec(&booth, 9, None).is_err());
    }

    #[test]
    fn a_monitor_not_at_the_projectors_native_mode_is_refused() {
        let spec = WindowSpec {
            projector: 1,
            monitor: 0,
            width: 1024,
            height: 768,
        };
        assert!(check_native_mode(&monitor("DP-1", 0, 0), &spec).is_ok());
        let mut wide = monitor("DP-1", 0, 0);
        wide.width = 1920;
        let err = check_native_mode(&wide, &spec).unwrap_err().to_string();
        assert!(err.contains("--mode 1024x768"), "{err}");
    }

    #[test]
    fn a_missing_monitor_names_the_ones_that_exist() {
        let monitors = number_monitors(vec![monitor("DP-1", 0, 0), monitor("DP-2", 1024, 0)]);
        let err = find_monitor(&monitors, 3, 2).unwrap_err().to_string();
        assert!(err.contains("projector 2"), "{err}");
        assert!(err.contains("monitor 3"), "{err}");
        assert!(err.contains("0 \"DP-1\" 1024x768+0+0 @ 60.00 Hz"), "{err}");
        assert!(err.contains("1 \"DP-2\" 1024x768+1024+0"), "{err}");
        assert_eq!(find_monitor(&monitors, 1, 0).unwrap().name, "DP-2");
    }
}
