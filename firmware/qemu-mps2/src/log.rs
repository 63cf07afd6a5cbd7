//! defmt global logger writing frames to UART1, never blocking: a byte that finds the transmit
//! buffer full is dropped. The protocol on UART0 is never touched.

use core::sync::atomic::{AtomicBool, Ordering};

use crate::cmsdk::Uart;

#[defmt::global_logger]
struct Uart1Logger;

static TAKEN: AtomicBool = AtomicBool::new(false);
static mut RESTORE: critical_section::RestoreState = critical_section::RestoreState::invalid();
static mut ENCODER: defmt::Encoder = defmt::Encoder::new();

/// Enables UART1 for the log.
pub fn init() {
    let _ = Uart::new(Uart::UART1, 115_200);
}

fn write_bytes(bytes: &[u8]) {
    let uart = Uart::at(Uart::UART1);
    for &b in bytes {
        // Dropped when full: logging must never hold up the controller.
        let _ = uart.try_write(b);
    }
}

// SAFETY: defmt calls acquire/release in pairs from any context; the critical section taken in
// `acquire` and restored in `release` makes the static encoder exclusive in between.
unsafe impl defmt::Logger for Uart1Logger {
    fn acquire() {
        // SAFETY: paired with the release in `release`.
        let restore = unsafe { critical_section::acquire() };
        if TAKEN.swap(true, Ordering::Relaxed) {
            panic!("defmt logger taken reentrantly");
        }
        // SAFETY: inside the critical section, with TAKEN set: no other access.
        unsafe {
            RESTORE = restore;
            (*core::ptr::addr_of_mut!(ENCODER)).start_frame(write_bytes);
        }
    }

    unsafe fn flush() {}

    unsafe fn release() {
        // SAFETY: called after `acquire` by defmt, still inside its critical section.
        unsafe {
            (*core::ptr::addr_of_mut!(ENCODER)).end_frame(write_bytes);
            TAKEN.store(false, Ordering::Relaxed);
            critical_section::release(RESTORE);
        }
    }

    unsafe fn write(bytes: &[u8]) {
        // SAFETY: called between `acquire` and `release`.
        unsafe { (*core::ptr::addr_of_mut!(ENCODER)).write(bytes, write_bytes) }
    }
}
