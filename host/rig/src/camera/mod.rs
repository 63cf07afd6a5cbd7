//! Real cameras (DESIGN section 7): USB3 Vision (GenICam) through `cameleon` over libusb.
//!
//! - [`pixels`]: payload bytes (Mono/Bayer 8 and 12 bit, packed or not) to linear RGB, with
//!   bilinear demosaicing.
//! - [`matching`]: payloads matched to trigger pulses by block id; dropped, incomplete,
//!   wrong-size and missing payloads and an unplugged camera reported per frame.
//! - [`u3v`]: the cameleon adapter (enumerate, open, configure, stream) and the
//!   [`u3v::U3vCamera`] backend.

pub mod matching;
pub mod pixels;
pub mod u3v;
