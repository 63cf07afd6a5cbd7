//! Fuzzes the streaming decoders of both directions with arbitrary bytes fed in arbitrary chunks.
//! Properties: no panic; every accepted message re-encodes to a frame that decodes to itself;
//! the counters add up.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mlsss_shared::framing::{Decoder, MAX_WIRE_FRAME_LEN, encode_frame};
use mlsss_shared::{ControllerMessage, HostMessage};
use serde::Serialize;
use serde::de::DeserializeOwned;

fn check<M: DeserializeOwned + Serialize + PartialEq + core::fmt::Debug>(data: &[u8]) {
    // The first byte chooses the chunk length, so split points are fuzzed too.
    let Some((&chunk, bytes)) = data.split_first() else {
        return;
    };
    let chunk = usize::from(chunk).max(1);
    let mut decoder = Decoder::<M>::new();
    let mut results = 0u32;
    for piece in bytes.chunks(chunk) {
        for result in decoder.feed(piece) {
            results += 1;
            if let Ok(received) = result {
                let mut buf = [0u8; MAX_WIRE_FRAME_LEN];
                let len = encode_frame(received.seq, &received.message, &mut buf)
                    .expect("an accepted message always re-encodes");
                let mut again = Decoder::<M>::new();
                let decoded: Vec<_> = again.feed(&buf[..len]).collect();
                assert!(matches!(decoded.as_slice(), [Ok(r)] if r.message == received.message));
            }
        }
    }
    let s = decoder.stats();
    assert_eq!(s.resyncs, s.crc_errors + s.malformed + s.oversize);
    assert_eq!(results, s.frames_ok + s.resyncs);
}

fuzz_target!(|data: &[u8]| {
    check::<HostMessage>(data);
    check::<ControllerMessage>(data);
});
