//! Matching camera payloads to trigger events. With the camera in hardware-trigger mode every
//! trigger pulse the controller fires makes exactly one payload, and the camera numbers its
//! payloads (block ids) consecutively; so the n-th `Triggered` event of a run (0-based, retries
//! included) is block `first_block_id + n`. A gap in the block ids is a dropped payload, a
//! pulse with no payload before the timeout is a trigger the camera missed, and every such case
//! is reported for the frame it belongs to: nothing is lost silently.

use std::collections::VecDeque;
use std::time::Duration;

use image::Rgb32FImage;

use super::pixels::{PixelLayout, decode};

/// One payload as the camera delivered it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RawPayload {
    /// The camera's block id.
    pub block_id: u64,
    /// Image width the payload's leader announces.
    pub width: u32,
    /// Image height the payload's leader announces.
    pub height: u32,
    /// The pixel format's PFNC name.
    pub pixel_format: String,
    /// Whether the transport delivered the whole payload (the trailer's status).
    pub complete: bool,
    /// Image bytes.
    pub data: Vec<u8>,
}

/// Why the next payload could not be had.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SourceError {
    /// Nothing arrived before the timeout.
    #[error("no payload within the timeout")]
    Timeout,
    /// The camera is gone (unplugged, reset).
    #[error("the camera was disconnected")]
    Disconnected,
    /// Another transport error.
    #[error("stream: {0}")]
    Stream(String),
}

/// Where payloads come from: a camera stream, or a recording in tests.
pub trait PayloadSource: Send {
    /// The next payload, waiting at most `timeout`.
    fn next_payload(&mut self, timeout: Duration) -> Result<RawPayload, SourceError>;
}

/// What went wrong with the payload of one triggered frame.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PayloadError {
    /// The trigger fired but no payload came.
    #[error("frame {frame}: triggered, but no payload (block {block}) arrived within {waited:?}")]
    NoPayload {
        frame: u32,
        block: u64,
        waited: Duration,
    },
    /// The camera skipped this frame's block (lost on the bus or in its buffers).
    #[error("frame {frame}: payload dropped (block {block} missing, block {next} came next)")]
    Dropped { frame: u32, block: u64, next: u64 },
    /// The payload arrived incomplete.
    #[error("frame {frame}: payload (block {block}) incomplete, {got} of {want} bytes")]
    Incomplete {
        frame: u32,
        block: u64,
        got: usize,
        want: usize,
    },
    /// The payload's size or geometry is not what the camera was configured for.
    #[error("frame {frame}: payload (block {block}) is {got}, expected {want}")]
    WrongSize {
        frame: u32,
        block: u64,
        got: String,
        want: String,
    },
    /// The payload's pixel format is not one the backend decodes.
    #[error("frame {frame}: unsupported pixel format {format}")]
    PixelFormat { frame: u32, format: String },
    /// The camera went away.
    #[error("frame {frame}: the camera was disconnected")]
    Disconnected { frame: u32 },
    /// Another stream error.
    #[error("frame {frame}: {message}")]
    Stream { frame: u32, message: String },
}

/// Payloads matched to trigger pulses in order.
pub struct TriggerMatcher<S> {
    source: S,
    width: u32,
    height: u32,
    /// Block id of the next trigger pulse.
    next_block: u64,
    timeout: Duration,
    /// Payloads that arrived ahead of their pulse (after a dropped one).
    early: VecDeque<RawPayload>,
    /// Stale payloads (block ids already passed) discarded, for the report.
    pub discarded: u64,
}

impl<S: PayloadSource> TriggerMatcher<S> {
    /// Expects `width` x `height` images, the first pulse making block `first_block_id`.
    pub fn new(
        source: S,
        (width, height): (u32, u32),
        first_block_id: u64,
        timeout: Duration,
    ) -> Self {
        Self {
            source,
            width,
            height,
            next_block: first_block_id,
            timeout,
            early: VecDeque::new(),
            discarded: 0,
        }
    }

    /// The image of the next trigger pulse, which fired for `frame`.
    pub fn next_image(&mut self, frame: u32) -> Result<Rgb32FImage, PayloadError> {
        let block = self.next_block;
        self.next_block += 1;
        let payload = self.payload_for(frame, block)?;
        self.check_and_decode(frame, payload)
    }

    fn payload_for(&mut self, frame: u32, block: u64) -> Result<RawPayload, PayloadError> {
        if let Some(early) = self.early.pop_front() {
            return self.accept(frame, block, early);
        }
        loop {
            let payload = self
                .source
                .next_payload(self.timeout)
                .map_err(|e| match e {
                    SourceError::Timeout => PayloadError::NoPayload {
                        frame,
                        block,
                        waited: self.timeout,
                    },
                    SourceError::Disconnected => PayloadError::Disconnected { frame },
                    SourceError::Stream(message) => PayloadError::Stream { frame, message },
                })?;
            if payload.block_id < block {
                self.discarded += 1; // a leftover of an earlier pulse, already reported
                continue;
            }
            return self.accept(frame, block, payload);
        }
    }

    fn accept(
        &mut self,
        frame: u32,
        block: u64,
        payload: RawPayload,
    ) -> Result<RawPayload, PayloadError> {
        if payload.block_id == block {
            return Ok(payload);
        }
        let next = payload.block_id;
        self.early.push_front(payload);
        Err(PayloadError::Dropped { frame, block, next })
    }

    fn check_and_decode(
        &self,
        frame: u32,
        payload: RawPayload,
    ) -> Result<Rgb32FImage, PayloadError> {
        let layout = PixelLayout::from_pfnc(&payload.pixel_format).ok_or_else(|| {
            PayloadError::PixelFormat {
                frame,
                format: payload.pixel_format.clone(),
            }
        })?;
        let want = layout.image_bytes(self.width, self.height);
        if !payload.complete {
            return Err(PayloadError::Incomplete {
                frame,
                block: payload.block_id,
                got: payload.data.len(),
                want,
            });
        }
        if (payload.width, payload.height) != (self.width, self.height)
            || payload.data.len() != want
        {
            return Err(PayloadError::WrongSize {
                frame,
                block: payload.block_id,
                got: format!(
                    "{}x{}, {} bytes",
                    payload.width,
                    payload.height,
                    payload.data.len()
                ),
                want: format!("{}x{}, {want} bytes", self.width, self.height),
            });
        }
        decode(layout, self.width, self.height, &payload.data).ok_or(PayloadError::WrongSize {
            frame,
            block: payload.block_id,
            got: format!("{} bytes", payload.data.len()),
            want: format!("{want} bytes"),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A recorded stream: what the camera delivered, in order, then `end`.
    struct Recording {
        events: VecDeque<Result<RawPayload, SourceError>>,
        end: SourceError,
    }

    impl PayloadSource for Recording {
        fn next_payload(&mut self, _timeout: Duration) -> Result<RawPayload, SourceError> {
            self.events.pop_front().unwrap_or(Err(self.end.clone()))
        }
    }

    /// A 4x2 Mono8 payload whose pixels all equal its block id (so a test can tell images apart).
    fn payload(block_id: u64) -> RawPayload {
        RawPayload {
            block_id,
            width: 4,
            height: 2,
            pixel_format: "Mono8".into(),
            complete: true,
            data: vec![block_id as u8; 8],
        }
    }

    fn matcher(
        events: Vec<Result<RawPayload, SourceError>>,
        end: SourceError,
    ) -> TriggerMatcher<Recording> {
        let source = Recording {
            events: events.into(),
            end,
        };
        TriggerMatcher::new(source, (4, 2), 1, Duration::from_millis(300))
    }

    fn block_of(img: &Rgb32FImage) -> u64 {
        (img.get_pixel(0, 0).0[0] * 255.0).round() as u64
    }

    #[test]
    fn payloads_match_trigger_pulses_by_block_id() {
        let mut m = matcher(
            vec![Ok(payload(1)), Ok(payload(2)), Ok(payload(3))],
            SourceError::Timeout,
        );
        for (frame, block) in [(0, 1), (1, 2), (1, 3)] {
            // Frame 1 twice: a re-triggered frame makes a second pulse and a second payload.
            assert_eq!(block_of(&m.next_image(frame).unwrap()), block);
        }
    }

    #[test]
    fn a_trigger_without_a_payload_is_reported_for_its_frame() {
        let mut m = matcher(vec![Ok(payload(1))], SourceError::Timeout);
        assert!(m.next_image(0).is_ok());
        assert_eq!(
            m.next_image(1).unwrap_err(),
            PayloadError::NoPayload {
                frame: 1,
                block: 2,
                waited: Duration::from_millis(300)
            }
        );
    }

    #[test]
    fn a_dropped_payload_is_reported_and_the_next_one_still_matches_its_own_pulse() {
        let mut m = matcher(
            vec![Ok(payload(1)), Ok(payload(3)), Ok(payload(4))],
            SourceError::Timeout,
        );
        assert_eq!(block_of(&m.next_image(0).unwrap()), 1);
        assert_eq!(
            m.next_image(1).unwrap_err(),
            PayloadError::Dropped {
                frame: 1,
                block: 2,
                next: 3
            }
        );
        assert_eq!(block_of(&m.next_image(2).unwrap()), 3);
        assert_eq!(block_of(&m.next_image(3).unwrap()), 4);
    }

    #[test]
    fn stale_payloads_are_skipped_and_counted() {
        let mut m = matcher(vec![Ok(payload(0)), Ok(payload(1))], SourceError::Timeout);
        assert_eq!(block_of(&m.next_image(0).unwrap()), 1);
        assert_eq!(m.discarded, 1);
    }

    #[test]
    fn a_payload_of_the_wrong_size_is_an_error_not_an_image() {
        let mut short = payload(1);
        short.data.pop();
        let mut other_geometry = payload(2);
        other_geometry.width = 8;
        other_geometry.height = 1;
        let mut m = matcher(vec![Ok(short), Ok(other_geometry)], SourceError::Timeout);
        for frame in 0..2 {
            let err = m.next_image(frame).unwrap_err();
            assert!(matches!(err, PayloadError::WrongSize { .. }), "{err}");
        }
    }

    #[test]
    fn an_incomplete_payload_is_reported() {
        let mut partial = payload(1);
        partial.complete = false;
        partial.data.truncate(3);
        let mut m = matcher(vec![Ok(partial)], SourceError::Timeout);
        assert_eq!(
            m.next_image(0).unwrap_err(),
            PayloadError::Incomplete {
                frame: 0,
                block: 1,
                got: 3,
                want: 8
            }
        );
    }

    #[test]
    fn a_camera_unplugged_mid_run_fails_the_next_frame() {
        let mut m = matcher(vec![Ok(payload(1))], SourceError::Disconnected);
        assert!(m.next_image(0).is_ok());
        assert_eq!(
            m.next_image(1).unwrap_err(),
            PayloadError::Disconnected { frame: 1 }
        );
    }

    #[test]
    fn an_unsupported_pixel_format_is_named() {
        let mut rgb = payload(1);
        rgb.pixel_format = "RGB8".into();
        let mut m = matcher(vec![Ok(rgb)], SourceError::Timeout);
        let err = m.next_image(0).unwrap_err().to_string();
        assert!(err.contains("RGB8"), "{err}");
    }
}
