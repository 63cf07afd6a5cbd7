//! Minimal drivers for the CMSDK peripherals QEMU models on `mps2-an386` (no PAC exists):
//! APB UART, APB timer, APB dual timer. Register offsets from the Cortex-M System Design Kit
//! TRM (ARM DDI 0479C); base addresses and IRQ numbers from QEMU `hw/arm/mps2.c`.

use core::convert::Infallible;
use core::ptr::{read_volatile, write_volatile};

/// Peripheral clock of the board (QEMU `SYSCLK_FRQ`), Hz.
pub const SYSCLK_HZ: u32 = 25_000_000;

/// A 32-bit memory-mapped register block at a fixed address.
#[derive(Clone, Copy)]
struct Regs(usize);

impl Regs {
    fn read(self, offset: usize) -> u32 {
        // SAFETY: the addresses are the board's device registers (QEMU mps2 memory map), always
        // mapped, 4-byte aligned, with no side effects beyond the device's own.
        unsafe { read_volatile((self.0 + offset) as *const u32) }
    }

    fn write(self, offset: usize, value: u32) {
        // SAFETY: as in `read`.
        unsafe { write_volatile((self.0 + offset) as *mut u32, value) }
    }
}

/// CMSDK APB UART.
pub struct Uart(Regs);

const UART_DATA: usize = 0x00;
const UART_STATE: usize = 0x04;
const UART_CTRL: usize = 0x08;
const UART_BAUDDIV: usize = 0x10;
const STATE_TX_FULL: u32 = 1 << 0;
const STATE_RX_FULL: u32 = 1 << 1;
const CTRL_TX_EN: u32 = 1 << 0;
const CTRL_RX_EN: u32 = 1 << 1;

impl Uart {
    /// UART0 (0x4000_4000): the protocol link (QEMU's first `-serial`).
    pub const UART0: usize = 0x4000_4000;
    /// UART1 (0x4000_5000): defmt log frames (QEMU's second `-serial`, if any).
    pub const UART1: usize = 0x4000_5000;

    /// Enables transmit and receive at `baud` (QEMU ignores the rate but needs a divider >= 16).
    pub fn new(base: usize, baud: u32) -> Self {
        let uart = Self(Regs(base));
        uart.0.write(UART_BAUDDIV, (SYSCLK_HZ / baud).max(16));
        uart.0.write(UART_CTRL, CTRL_TX_EN | CTRL_RX_EN);
        uart
    }

    /// An already enabled UART.
    pub const fn at(base: usize) -> Self {
        Self(Regs(base))
    }

    /// Sends a byte unless the transmit buffer is full; returns whether it was sent.
    pub fn try_write(&self, byte: u8) -> bool {
        if self.0.read(UART_STATE) & STATE_TX_FULL != 0 {
            return false;
        }
        self.0.write(UART_DATA, u32::from(byte));
        true
    }

    fn rx_full(&self) -> bool {
        self.0.read(UART_STATE) & STATE_RX_FULL != 0
    }
}

impl embedded_io::ErrorType for Uart {
    type Error = Infallible;
}

impl embedded_io::ReadReady for Uart {
    fn read_ready(&mut self) -> Result<bool, Infallible> {
        Ok(self.rx_full())
    }
}

impl embedded_io::Read for Uart {
    /// Blocks for the first byte (as `embedded_io::Read` requires), then takes what is there.
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Infallible> {
        let mut n = 0;
        for slot in buf.iter_mut() {
            if n > 0 && !self.rx_full() {
                break;
            }
            while !self.rx_full() {}
            *slot = self.0.read(UART_DATA) as u8;
            n += 1;
        }
        Ok(n)
    }
}

impl embedded_io::Write for Uart {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Infallible> {
        for &byte in buf {
            while !self.try_write(byte) {}
        }
        Ok(buf.len())
    }

    fn flush(&mut self) -> Result<(), Infallible> {
        while self.0.read(UART_STATE) & STATE_TX_FULL != 0 {}
        Ok(())
    }
}

/// CMSDK APB timer: a 32-bit down-counter reloading from `RELOAD` (period `RELOAD + 1` ticks).
pub struct Timer(Regs);

const TIMER_CTRL: usize = 0x00;
const TIMER_VALUE: usize = 0x04;
const TIMER_RELOAD: usize = 0x08;
const TIMER_INTCLEAR: usize = 0x0C;
const TIMER_CTRL_ENABLE: u32 = 1 << 0;
const TIMER_CTRL_IRQ_ENABLE: u32 = 1 << 3;

impl Timer {
    /// TIMER0 (0x4000_0000, IRQ 8).
    pub const TIMER0: usize = 0x4000_0000;
    /// TIMER1 (0x4000_1000, IRQ 9).
    pub const TIMER1: usize = 0x4000_1000;

    /// Starts counting down from `first` and then every `period` ticks, with or without the
    /// interrupt at each wrap.
    pub fn start(base: usize, first: u32, period: u32, interrupt: bool) -> Self {
        let t = Self(Regs(base));
        t.0.write(TIMER_CTRL, 0);
        t.0.write(TIMER_RELOAD, period.wrapping_sub(1));
        t.0.write(TIMER_VALUE, first);
        let irq = if interrupt { TIMER_CTRL_IRQ_ENABLE } else { 0 };
        t.0.write(TIMER_CTRL, TIMER_CTRL_ENABLE | irq);
        t
    }

    /// The same timer, for an interrupt handler.
    pub const fn at(base: usize) -> Self {
        Self(Regs(base))
    }

    /// Stops (`false`) or continues (`true`) the count where it stands, keeping the reload and
    /// the interrupt setting (QEMU stops and restarts the timer's deadline with it).
    pub fn set_running(&self, running: bool) {
        let ctrl = self.0.read(TIMER_CTRL) & !TIMER_CTRL_ENABLE;
        let enable = if running { TIMER_CTRL_ENABLE } else { 0 };
        self.0.write(TIMER_CTRL, ctrl | enable);
    }

    /// Sets the count of a stopped timer (what `value` reads until it is started).
    pub fn preset(&self, value: u32) {
        self.0.write(TIMER_VALUE, value);
    }

    /// Current count (down-counting).
    pub fn value(&self) -> u32 {
        self.0.read(TIMER_VALUE)
    }

    /// Ticks since the last wrap (the VSYNC edge this timer stands for).
    pub fn ticks_since_wrap(&self) -> u32 {
        self.0.read(TIMER_RELOAD).wrapping_sub(self.value())
    }

    /// Acknowledges the interrupt.
    pub fn clear_interrupt(&self) {
        self.0.write(TIMER_INTCLEAR, 1);
    }
}

/// One counter of the CMSDK APB dual timer, periodic 32-bit mode.
pub struct DualTimer(Regs);

const DT_LOAD: usize = 0x00;
const DT_VALUE: usize = 0x04;
const DT_CONTROL: usize = 0x08;
const DT_INTCLR: usize = 0x0C;
const DT_MIS: usize = 0x14;
const DT_BGLOAD: usize = 0x18;
const DT_CONTROL_32BIT: u32 = 1 << 1;
const DT_CONTROL_INTEN: u32 = 1 << 5;
const DT_CONTROL_PERIODIC: u32 = 1 << 6;
const DT_CONTROL_ENABLE: u32 = 1 << 7;

impl DualTimer {
    /// Counter 1 of the dual timer (0x4000_2000; both counters share IRQ 10).
    pub const COUNTER1: usize = 0x4000_2000;
    /// Counter 2 of the dual timer.
    pub const COUNTER2: usize = 0x4000_2020;

    /// Starts counting down from `first`, then every `period` ticks, interrupting at each wrap.
    pub fn start(base: usize, first: u32, period: u32) -> Self {
        let t = Self(Regs(base));
        t.0.write(DT_CONTROL, 0);
        t.0.write(DT_LOAD, first);
        // The background load takes effect at the next wrap without restarting the count.
        t.0.write(DT_BGLOAD, period.wrapping_sub(1));
        t.0.write(
            DT_CONTROL,
            DT_CONTROL_ENABLE | DT_CONTROL_PERIODIC | DT_CONTROL_INTEN | DT_CONTROL_32BIT,
        );
        t
    }

    /// The same counter, for an interrupt handler.
    pub const fn at(base: usize) -> Self {
        Self(Regs(base))
    }

    /// Stops (`false`) or continues (`true`) the count where it stands, keeping the mode.
    pub fn set_running(&self, running: bool) {
        let control = self.0.read(DT_CONTROL) & !DT_CONTROL_ENABLE;
        let enable = if running { DT_CONTROL_ENABLE } else { 0 };
        self.0.write(DT_CONTROL, control | enable);
    }

    /// True when this counter's interrupt is pending.
    pub fn pending(&self) -> bool {
        self.0.read(DT_MIS) & 1 != 0
    }

    /// Ticks since the last wrap.
    pub fn ticks_since_wrap(&self) -> u32 {
        self.0.read(DT_BGLOAD).wrapping_sub(self.0.read(DT_VALUE))
    }

    /// Acknowledges the interrupt.
    pub fn clear_interrupt(&self) {
        self.0.write(DT_INTCLR, 1);
    }
}

/// The FPGA I/O block's LED register: LED0 stands for the camera trigger output.
pub struct FpgaLed;

/// FPGAIO LED register (QEMU `mps2-fpgaio` at 0x4002_8000).
const FPGAIO_LED0: usize = 0x4002_8000;
/// FPGAIO 100 Hz up-counter (`CLK100HZ`, offset 0x14 in QEMU `hw/misc/mps2-fpgaio.c`),
/// free-running on QEMU's virtual clock.
const FPGAIO_CLK100HZ: usize = 0x14;

/// Centiseconds of QEMU virtual time since reset, from the FPGAIO 100 Hz counter: a clock the
/// firmware never stops (unlike the booth timers), so it measures how long the host was waited
/// for.
pub fn virtual_centiseconds() -> u32 {
    Regs(FPGAIO_LED0).read(FPGAIO_CLK100HZ)
}

impl embedded_hal::digital::ErrorType for FpgaLed {
    type Error = Infallible;
}

impl embedded_hal::digital::OutputPin for FpgaLed {
    fn set_low(&mut self) -> Result<(), Infallible> {
        Regs(FPGAIO_LED0).write(0, 0);
        Ok(())
    }

    fn set_high(&mut self) -> Result<(), Infallible> {
        Regs(FPGAIO_LED0).write(0, 1);
        Ok(())
    }
}
