//! Booth controller firmware for the STM32F446RE Nucleo-64 board (pin map: hardware/wiring.md).
//!
//! - USART2 (PA2 TX / PA3 RX, the ST-LINK virtual COM port, 921 600 baud): the wire protocol.
//!   Received bytes are queued by the RXNE interrupt (a blocking wait near a trigger must not
//!   overrun the one-byte receive register).
//! - TIM2: free-running 32-bit counter at 1 MHz, extended to the 64-bit microsecond clock; its
//!   compare channel 1 is the alarm that wakes the main loop from WFI.
//! - VSYNC of projectors 0-3 on PC0-PC3 (EXTI0-3, rising edge), timestamped in the interrupt.
//! - Camera trigger output PA8; camera exposure-active input PA9.
//! - defmt logs over RTT (probe-rs / the ST-LINK), never on the protocol UART.
#![no_std]
#![no_main]

use core::cell::RefCell;

use cortex_m_rt::entry;
use critical_section::Mutex;
use defmt_rtt as _;
use embedded_io::{ErrorType, Read, ReadReady, Write};
use heapless::spsc::Queue;
use mlsss_sequencer::{BoardInfo, Controller, CounterExtender, MonotonicClock};
use mlsss_shared::message::Board;
use panic_probe as _;
use stm32f4xx_hal::gpio::{Edge, ExtiPin, Input, Output, PA8, PA9};
use stm32f4xx_hal::pac::{self, interrupt};
use stm32f4xx_hal::prelude::*;
use stm32f4xx_hal::rcc::Config;
use stm32f4xx_hal::serial::{self, Rx, RxListen, Serial, Tx};

/// Protocol baud rate: a 40-byte frame takes 0.43 ms, well inside the controller's I/O guard.
const BAUD: u32 = 921_600;

/// VSYNC edges from the EXTI handlers: (projector, time in us).
static VSYNC_EDGES: Mutex<RefCell<Queue<(u8, u64), 32>>> = Mutex::new(RefCell::new(Queue::new()));
/// Bytes from the USART2 receive interrupt.
static RX_BYTES: Mutex<RefCell<Queue<u8, 512>>> = Mutex::new(RefCell::new(Queue::new()));
/// Bytes dropped because `RX_BYTES` was full (the decoder then sees a corrupt frame).
static RX_OVERFLOWS: Mutex<RefCell<u32>> = Mutex::new(RefCell::new(0));
/// The receive half of USART2, owned by its interrupt handler.
static RX: Mutex<RefCell<Option<Rx<pac::USART2>>>> = Mutex::new(RefCell::new(None));
/// The 64-bit extension of TIM2.
static CLOCK: Mutex<RefCell<CounterExtender>> = Mutex::new(RefCell::new(CounterExtender::new()));

fn tim2() -> &'static pac::tim2::RegisterBlock {
    // SAFETY: TIM2 is configured once in `main`; afterwards only its counter, compare register
    // and status flags are touched, each access a single volatile register operation.
    unsafe { &*pac::TIM2::ptr() }
}

/// Microseconds since boot.
fn now_us() -> u64 {
    critical_section::with(|cs| {
        let raw = tim2().cnt().read().bits();
        CLOCK.borrow_ref_mut(cs).extend(raw)
    })
}

/// The TIM2 microsecond clock with its compare channel 1 as the alarm.
struct Tim2Clock;

impl MonotonicClock for Tim2Clock {
    fn now_us(&mut self) -> u64 {
        now_us()
    }

    fn set_alarm(&mut self, at_us: u64) {
        // The compare matches the low 32 bits; alarms are never more than seconds ahead.
        tim2().ccr1().write(|w| w.ccr().set(at_us as u32));
        tim2().sr().modify(|_, w| w.cc1if().clear_bit());
        tim2().dier().modify(|_, w| w.cc1ie().set_bit());
    }

    fn wait_until(&mut self, at_us: u64) -> u64 {
        loop {
            let now = now_us();
            if now >= at_us {
                return now;
            }
        }
    }
}

/// USART2: receive from the interrupt queue, transmit blocking.
struct Usart2 {
    tx: Tx<pac::USART2>,
}

impl ErrorType for Usart2 {
    type Error = serial::Error;
}

impl ReadReady for Usart2 {
    fn read_ready(&mut self) -> Result<bool, serial::Error> {
        Ok(critical_section::with(|cs| {
            !RX_BYTES.borrow_ref(cs).is_empty()
        }))
    }
}

impl Read for Usart2 {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, serial::Error> {
        loop {
            let n = critical_section::with(|cs| {
                let mut q = RX_BYTES.borrow_ref_mut(cs);
                let mut n = 0;
                for slot in buf.iter_mut() {
                    match q.dequeue() {
                        Some(b) => *slot = b,
                        None => break,
                    }
                    n += 1;
                }
                n
            });
            if n > 0 || buf.is_empty() {
                return Ok(n);
            }
        }
    }
}

impl Write for Usart2 {
    fn write(&mut self, buf: &[u8]) -> Result<usize, serial::Error> {
        Write::write(&mut self.tx, buf)
    }

    fn flush(&mut self) -> Result<(), serial::Error> {
        Write::flush(&mut self.tx)
    }
}

/// The controller of this board.
type NucleoController = Controller<Usart2, TriggerPin, ExposurePin, Tim2Clock, 4>;

/// Camera trigger output, PA8.
type TriggerPin = PA8<Output>;
/// Camera exposure-active input, PA9.
type ExposurePin = PA9<Input>;

#[entry]
fn main() -> ! {
    let Some(dp) = pac::Peripherals::take() else {
        panic!("peripherals taken twice");
    };
    // 8 MHz from the ST-LINK's MCO (HSE bypass), PLL to 180 MHz.
    let mut rcc = dp.RCC.freeze(
        Config::hse(8.MHz())
            .bypass_hse_oscillator()
            .sysclk(180.MHz()),
    );
    let mut syscfg = dp.SYSCFG.constrain(&mut rcc);
    let mut exti = dp.EXTI;
    let gpioa = dp.GPIOA.split(&mut rcc);
    let gpioc = dp.GPIOC.split(&mut rcc);

    // The microsecond clock: TIM2 at 1 MHz, full 32-bit range.
    let mut counter = dp.TIM2.counter_us(&mut rcc);
    if counter.start(1_000_000.micros()).is_err() {
        panic!("TIM2 start");
    }
    tim2().arr().write(|w| w.arr().set(u32::MAX));

    // VSYNC inputs: rising edges on PC0..PC3 (one EXTI line each).
    let mut vsync_pins = (
        gpioc.pc0.into_pull_down_input(),
        gpioc.pc1.into_pull_down_input(),
        gpioc.pc2.into_pull_down_input(),
        gpioc.pc3.into_pull_down_input(),
    );
    macro_rules! vsync_input {
        ($pin:expr) => {
            $pin.make_interrupt_source(&mut syscfg);
            $pin.trigger_on_edge(&mut exti, Edge::Rising);
            $pin.enable_interrupt(&mut exti);
        };
    }
    vsync_input!(vsync_pins.0);
    vsync_input!(vsync_pins.1);
    vsync_input!(vsync_pins.2);
    vsync_input!(vsync_pins.3);

    let serial: Serial<pac::USART2> = match Serial::new(
        dp.USART2,
        (gpioa.pa2, gpioa.pa3),
        serial::Config::default().baudrate(BAUD.bps()),
        &mut rcc,
    ) {
        Ok(s) => s,
        Err(_) => panic!("USART2 configuration"),
    };
    let (tx, mut rx) = serial.split();
    rx.listen();
    critical_section::with(|cs| RX.borrow_ref_mut(cs).replace(rx));

    let trigger: TriggerPin = gpioa.pa8.into_push_pull_output();
    #[cfg(feature = "exposure-input")]
    let exposure: Option<ExposurePin> = Some(gpioa.pa9.into_pull_down_input());
    #[cfg(not(feature = "exposure-input"))]
    let exposure: Option<ExposurePin> = None;

    // SAFETY: the handlers only touch their own EXTI line / USART2 and the statics above.
    unsafe {
        for irq in [
            pac::Interrupt::EXTI0,
            pac::Interrupt::EXTI1,
            pac::Interrupt::EXTI2,
            pac::Interrupt::EXTI3,
            pac::Interrupt::USART2,
            pac::Interrupt::TIM2,
        ] {
            pac::NVIC::unmask(irq);
        }
    }

    let info = BoardInfo {
        board: Board::Stm32f4Nucleo,
        firmware_version: [0, 1, 0],
        timer_tick_ns: 1000,
    };
    let Ok(controller) =
        Controller::<_, _, _, _, 4>::new(Usart2 { tx }, trigger, exposure, Tim2Clock, info)
    else {
        panic!("controller");
    };
    // In a static, so the RAM report of the image (.bss) includes the controller and its
    // schedule buffers.
    let Some(controller) = cortex_m::singleton!(: NucleoController = controller) else {
        panic!("controller placed twice");
    };
    defmt::info!("mlsss-fw-nucleo {} ready", env!("CARGO_PKG_VERSION"));

    loop {
        while let Some((projector, t)) =
            critical_section::with(|cs| VSYNC_EDGES.borrow_ref_mut(cs).dequeue())
        {
            controller.on_vsync(projector, t);
        }
        let next = match controller.poll() {
            Ok(next) => next,
            Err(e) => {
                defmt::warn!("controller: {}", defmt::Debug2Format(&e));
                None
            }
        };
        // Sleep until an interrupt (VSYNC edge, received byte, the alarm) unless something is
        // already waiting or due. Interrupts are masked while checking so an event arriving
        // between the check and WFI still wakes it (WFI wakes on pending interrupts).
        critical_section::with(|cs| {
            let idle = VSYNC_EDGES.borrow_ref(cs).is_empty() && RX_BYTES.borrow_ref(cs).is_empty();
            let due = next.is_some_and(|at| at <= now_us() + 2);
            if idle && !due {
                cortex_m::asm::wfi();
            }
        });
    }
}

/// Queues a VSYNC edge of `projector` timestamped now and acknowledges EXTI `line`.
fn vsync_edge(projector: u8, line: u8) {
    let t = now_us();
    // SAFETY: writing 1 to a pending bit of EXTI_PR clears only that line.
    unsafe { (*pac::EXTI::ptr()).pr().write(|w| w.bits(1 << line)) };
    critical_section::with(|cs| {
        // A full queue means the main loop stalled for 32 edges; the missing edge is then
        // detected by the sequencer as a VSYNC gap.
        let _ = VSYNC_EDGES.borrow_ref_mut(cs).enqueue((projector, t));
    });
}

#[interrupt]
fn EXTI0() {
    vsync_edge(0, 0);
}

#[interrupt]
fn EXTI1() {
    vsync_edge(1, 1);
}

#[interrupt]
fn EXTI2() {
    vsync_edge(2, 2);
}

#[interrupt]
fn EXTI3() {
    vsync_edge(3, 3);
}

#[interrupt]
fn USART2() {
    critical_section::with(|cs| {
        let mut rx = RX.borrow_ref_mut(cs);
        let Some(rx) = rx.as_mut() else {
            return;
        };
        while let Ok(byte) = embedded_hal_nb::serial::Read::read(rx) {
            if RX_BYTES.borrow_ref_mut(cs).enqueue(byte).is_err() {
                *RX_OVERFLOWS.borrow_ref_mut(cs) += 1;
            }
        }
    });
}

#[interrupt]
fn TIM2() {
    // The alarm only wakes the main loop.
    tim2().sr().modify(|_, w| w.cc1if().clear_bit());
    tim2().dier().modify(|_, w| w.cc1ie().clear_bit());
}
