//! Properties of the framing: round trips, recovery from garbage, corruption, oversize frames and
//! sequence gaps.

mod samples;

use mlsss_shared::framing::{
    ControllerDecoder, Decoder, DecoderStats, Encoder, FrameError, HostDecoder, HostEncoder,
    MAX_WIRE_FRAME_LEN, Received,
};
use mlsss_shared::{ControllerMessage, HostMessage};
use proptest::prelude::*;
use serde::Serialize;
use serde::de::DeserializeOwned;

/// Number of variants of each direction's enum (the strategies pick the variant index uniformly).
const HOST_VARIANTS: u8 = 12;
const CONTROLLER_VARIANTS: u8 = 14;

/// Arbitrary valid messages: postcard decodings of a variant index followed by random bytes.
/// postcard is dense (varints, raw integers), so most random tails decode; the rest are skipped.
fn message<M: DeserializeOwned + std::fmt::Debug>(variants: u8) -> impl Strategy<Value = M> {
    (0..variants, proptest::collection::vec(any::<u8>(), 0..200)).prop_filter_map(
        "tail is not a valid message body",
        |(variant, tail)| {
            let mut bytes = vec![variant];
            bytes.extend(tail);
            postcard::take_from_bytes::<M>(&bytes).ok().map(|(m, _)| m)
        },
    )
}

fn host_message() -> impl Strategy<Value = HostMessage> {
    message(HOST_VARIANTS)
}

fn controller_message() -> impl Strategy<Value = ControllerMessage> {
    message(CONTROLLER_VARIANTS)
}

fn frame<M: Serialize>(encoder: &mut Encoder<M>, message: &M) -> Vec<u8> {
    let mut buf = [0u8; MAX_WIRE_FRAME_LEN];
    encoder.encode(message, &mut buf).unwrap().1.to_vec()
}

/// Feeds `stream` split at `cuts` (positions, any order, clamped) and collects every result.
fn feed_in_chunks<M: DeserializeOwned, const N: usize>(
    decoder: &mut Decoder<M, N>,
    stream: &[u8],
    cuts: &[usize],
) -> Vec<Result<Received<M>, FrameError>> {
    let mut cuts: Vec<usize> = cuts.iter().map(|&c| c % (stream.len() + 1)).collect();
    cuts.push(0);
    cuts.push(stream.len());
    cuts.sort_unstable();
    cuts.windows(2)
        .flat_map(|w| decoder.feed(&stream[w[0]..w[1]]).collect::<Vec<_>>())
        .collect()
}

#[test]
fn variant_counts_match_the_enums() {
    // A new variant must be added to the strategies above (and to the golden samples).
    assert!(postcard::from_bytes::<HostMessage>(&[HOST_VARIANTS]).is_err());
    // The last variant (Retrigger: frame and attempt) with zero fields.
    assert!(postcard::from_bytes::<HostMessage>(&[HOST_VARIANTS - 1, 0, 0]).is_ok());
    assert!(postcard::from_bytes::<ControllerMessage>(&[CONTROLLER_VARIANTS]).is_err());
    let names: std::collections::HashSet<_> = samples::controller_messages()
        .iter()
        .map(|(_, m)| std::mem::discriminant(m))
        .collect();
    assert_eq!(names.len(), usize::from(CONTROLLER_VARIANTS));
    let names: std::collections::HashSet<_> = samples::host_messages()
        .iter()
        .map(|(_, m)| std::mem::discriminant(m))
        .collect();
    assert_eq!(names.len(), usize::from(HOST_VARIANTS));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn host_messages_round_trip(messages in proptest::collection::vec(host_message(), 1..20),
                                cuts in proptest::collection::vec(any::<usize>(), 0..10)) {
        let mut encoder = HostEncoder::new();
        let stream: Vec<u8> = messages.iter().flat_map(|m| frame(&mut encoder, m)).collect();
        let mut decoder = HostDecoder::new();
        let results = feed_in_chunks(&mut decoder, &stream, &cuts);
        let received: Vec<_> = results.into_iter().map(|r| r.unwrap()).collect();
        prop_assert_eq!(received.len(), messages.len());
        for (i, (r, m)) in received.iter().zip(&messages).enumerate() {
            prop_assert_eq!(&r.message, m);
            prop_assert_eq!(usize::from(r.seq), i);
            prop_assert_eq!(r.missed, 0);
        }
    }

    #[test]
    fn controller_messages_round_trip(messages in proptest::collection::vec(controller_message(), 1..20)) {
        let mut encoder = Encoder::<ControllerMessage>::new();
        let stream: Vec<u8> = messages.iter().flat_map(|m| frame(&mut encoder, m)).collect();
        let mut decoder = ControllerDecoder::new();
        let received: Vec<_> = decoder.feed(&stream).map(|r| r.unwrap().message).collect();
        prop_assert_eq!(decoder.stats().frames_ok as usize, messages.len());
        prop_assert_eq!(received, messages);
    }

    /// Random garbage (zeros included) between valid frames: every valid frame that follows a
    /// delimiter is recovered in order, and nothing else is accepted.
    #[test]
    fn garbage_between_frames_never_hides_or_forges_a_frame(
        segments in proptest::collection::vec(
            (proptest::collection::vec(any::<u8>(), 0..300), controller_message()), 1..12),
        cuts in proptest::collection::vec(any::<usize>(), 0..20),
    ) {
        let mut encoder = Encoder::<ControllerMessage>::new();
        let mut stream = vec![];
        let mut sent = vec![];
        for (garbage, message) in &segments {
            stream.extend_from_slice(garbage);
            stream.push(0x00);
            stream.extend(frame(&mut encoder, message));
            sent.push(message.clone());
        }
        let mut decoder = ControllerDecoder::new();
        let results = feed_in_chunks(&mut decoder, &stream, &cuts);
        let accepted: Vec<_> = results.iter().filter_map(|r| r.as_ref().ok())
            .map(|r| r.message.clone()).collect();
        prop_assert_eq!(&accepted, &sent);
        let stats = decoder.stats();
        prop_assert_eq!(stats.frames_ok as usize, sent.len());
        prop_assert_eq!(stats.sequence_gaps, 0);
        let errors = results.iter().filter(|r| r.is_err()).count() as u32;
        prop_assert_eq!(errors, stats.resyncs);
        prop_assert_eq!(stats.resyncs, stats.crc_errors + stats.malformed + stats.oversize);
    }

    /// Pure garbage of any length is never accepted and never panics.
    #[test]
    fn garbage_alone_is_never_accepted(garbage in proptest::collection::vec(any::<u8>(), 0..2000)) {
        let mut decoder = HostDecoder::new();
        prop_assert!(decoder.feed(&garbage).all(|r| r.is_err()));
        prop_assert_eq!(decoder.stats().frames_ok, 0);
    }

    /// Flipping any bit of a frame makes the decoder reject it (CRC-32C catches every 1-bit
    /// error; a flip that creates a 0x00 splits the frame into two rejected pieces), and the
    /// next frame is recovered.
    #[test]
    fn a_flipped_bit_is_rejected_and_the_next_frame_recovered(
        message in host_message(), next in host_message(), bit in any::<usize>(),
    ) {
        let mut encoder = HostEncoder::new();
        let mut corrupted = frame(&mut encoder, &message);
        let body_bits = (corrupted.len() - 1) * 8; // leave the delimiter alone
        let bit = bit % body_bits;
        corrupted[bit / 8] ^= 1 << (bit % 8);
        let good = frame(&mut encoder, &next);
        let mut decoder = HostDecoder::new();
        let mut results: Vec<_> = decoder.feed(&corrupted).collect();
        prop_assert!(!results.is_empty() && results.iter().all(|r| r.is_err()));
        results = decoder.feed(&good).collect();
        prop_assert_eq!(results.len(), 1);
        let received = results.pop().unwrap().unwrap();
        prop_assert_eq!(received.message, next);
        // No frame was accepted before, so no gap can be known yet.
        prop_assert_eq!(received.missed, 0);
    }
}

#[test]
fn oversize_frame_is_counted_and_the_decoder_resyncs() {
    let mut encoder = HostEncoder::new();
    let (_, chunk) = samples::host_messages()
        .into_iter()
        .find(|(n, _)| *n == "schedule_chunk_full")
        .unwrap();
    let first = frame(&mut encoder, &HostMessage::Start);
    let big = frame(&mut encoder, &chunk);
    let small = frame(&mut encoder, &HostMessage::Arm);
    assert!(big.len() > 64 && small.len() <= 64);
    let mut decoder = Decoder::<HostMessage, 64>::new();
    let results: Vec<_> = decoder.feed(&[first, big, small].concat()).collect();
    assert_eq!(results.len(), 3);
    assert_eq!(results[1], Err(FrameError::Oversize));
    let received = results[2].clone().unwrap();
    assert_eq!(received.message, HostMessage::Arm);
    assert_eq!(received.missed, 1, "the oversize frame's number is missing");
    assert_eq!(
        decoder.stats(),
        DecoderStats {
            frames_ok: 2,
            oversize: 1,
            sequence_gaps: 1,
            resyncs: 1,
            ..DecoderStats::default()
        }
    );
}

#[test]
fn the_default_buffer_holds_the_largest_message() {
    // A full schedule chunk is the largest host message; it must fit the default decoder.
    let mut encoder = HostEncoder::new();
    for (name, message) in samples::host_messages() {
        let bytes = frame(&mut encoder, &message);
        let mut decoder = HostDecoder::new();
        let results: Vec<_> = decoder.feed(&bytes).collect();
        assert!(matches!(results.as_slice(), [Ok(_)]), "{name}");
    }
}

#[test]
fn sequence_gaps_are_reported_and_a_restart_is_not_a_gap() {
    let mut encoder = HostEncoder::new();
    let frames: Vec<Vec<u8>> = (0..6)
        .map(|_| frame(&mut encoder, &HostMessage::StatusQuery))
        .collect();
    let mut decoder = HostDecoder::new();
    let mut missed = vec![];
    for i in [0usize, 1, 4, 5] {
        missed.extend(decoder.feed(&frames[i]).map(|r| r.unwrap().missed));
    }
    assert_eq!(missed, [0, 0, 2, 0]);
    // A sender that restarts at 0 (reconnect) is not counted as 65531 lost frames.
    let mut restarted = HostEncoder::new();
    let again = frame(&mut restarted, &HostMessage::StatusQuery);
    let r: Vec<_> = decoder.feed(&again).collect();
    assert_eq!(r[0].as_ref().unwrap().missed, 0);
    assert_eq!(decoder.stats().sequence_gaps, 2);
}

#[test]
fn a_frame_of_the_other_direction_is_not_accepted_as_garbage() {
    // A controller Done frame decoded as a host message: its variant 10 is Resume, a unit
    // variant, so the trailing bytes make it invalid rather than a silent Resume.
    let mut encoder = Encoder::<ControllerMessage>::new();
    let (_, done) = samples::controller_messages()
        .into_iter()
        .find(|(n, _)| *n == "done_completed")
        .unwrap();
    let bytes = frame(&mut encoder, &done);
    let mut decoder = HostDecoder::new();
    let results: Vec<_> = decoder.feed(&bytes).collect();
    assert_eq!(results, [Err(FrameError::Deserialize)]);
}
