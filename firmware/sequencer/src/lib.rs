//! Sequencer core of the MLSSS booth controller (DESIGN section 7): runs a capture schedule of
//! frame slots, each locked to the VSYNC of the lit projector, fires the camera trigger on a
//! confirmed pattern after the settle VSYNCs, and reports every frame as triggered, late,
//! retried or dropped over the `mlsss-shared` wire protocol.
//!
//! `no_std`, no allocation (heapless), generic over embedded-hal 1.0 pins, embedded-io serial
//! ports and a [`clock::MonotonicClock`]; the board binaries (`mlsss-fw-qemu`,
//! `mlsss-fw-nucleo`) supply the peripherals, and the host tests supply mocks and a simulated
//! clock.
//!
//! - [`clock`]: the microsecond clock trait and 32 -> 64-bit counter extension.
//! - [`vsync`]: per-projector VSYNC counting and period measurement.
//! - [`schedule`]: schedule upload and validation (typed refusals).
//! - [`run`]: the timing rules of a run (slots, acks, settle, trigger, late/retry/abort).
//! - [`controller`]: the protocol session and the peripherals around a run.
#![cfg_attr(not(test), no_std)]

/// Logs through defmt when the `defmt` feature is on (the boards); expands to nothing otherwise
/// (host tests have no defmt logger), arguments included.
macro_rules! log {
    ($level:ident, $($arg:tt)*) => {
        #[cfg(feature = "defmt")]
        defmt::$level!($($arg)*);
    };
}

pub mod clock;
pub mod controller;
pub mod run;
pub mod schedule;
pub mod vsync;

pub use clock::{CounterExtender, MonotonicClock};
pub use controller::{BoardInfo, Controller, Error, NoExposureInput};
