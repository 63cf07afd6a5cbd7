//! Golden wire bytes of every message: any change of the encoding (field order, enum variant
//! order, framing, CRC) fails here. After a deliberate, versioned change, regenerate with
//! `MLSSS_BLESS=1 cargo test -p mlsss-shared --test golden` and review the diff.

mod samples;

use std::fmt::Write as _;

use mlsss_shared::framing::{Decoder, MAX_WIRE_FRAME_LEN, encode_frame};
use mlsss_shared::{ControllerMessage, HostMessage};
use serde::Serialize;
use serde::de::DeserializeOwned;

const GOLDEN_FILE: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/golden_frames.txt");

fn hex(bytes: &[u8]) -> String {
    bytes.iter().fold(String::new(), |mut s, b| {
        let _ = write!(s, "{b:02x}");
        s
    })
}

/// One line per message: `direction name seq hex-of-the-wire-frame`. The sequence number is the
/// message's position in its list, so the seq field is covered too.
fn encode_all<M: Serialize>(direction: &str, messages: &[(&str, M)], out: &mut String) {
    for (seq, (name, message)) in messages.iter().enumerate() {
        let mut buf = [0u8; MAX_WIRE_FRAME_LEN];
        let seq = seq as u16;
        let len = encode_frame(seq, message, &mut buf).expect("sample fits a frame");
        writeln!(out, "{direction} {name} {seq} {}", hex(&buf[..len])).unwrap();
    }
}

fn current_golden_text() -> String {
    let mut text = String::new();
    encode_all("host", &samples::host_messages(), &mut text);
    encode_all("controller", &samples::controller_messages(), &mut text);
    text
}

#[test]
fn every_message_matches_its_golden_bytes() {
    let current = current_golden_text();
    if std::env::var_os("MLSSS_BLESS").is_some() {
        std::fs::write(GOLDEN_FILE, &current).unwrap();
        return;
    }
    let golden = std::fs::read_to_string(GOLDEN_FILE).expect("tests/golden_frames.txt exists");
    let mut mismatches = vec![];
    for (want, got) in golden.lines().zip(current.lines()) {
        if want != got {
            mismatches.push(format!("  golden:  {want}\n  current: {got}"));
        }
    }
    assert_eq!(
        golden.lines().count(),
        current.lines().count(),
        "number of golden messages changed"
    );
    assert!(
        mismatches.is_empty(),
        "wire format changed (bump PROTOCOL_VERSION and re-bless deliberately):\n{}",
        mismatches.join("\n")
    );
}

fn unhex(s: &str) -> Vec<u8> {
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap())
        .collect()
}

fn decode_golden<M: DeserializeOwned + PartialEq + std::fmt::Debug>(
    direction: &str,
    samples: &[(&str, M)],
) {
    let golden = std::fs::read_to_string(GOLDEN_FILE).unwrap();
    let mut decoder = Decoder::<M>::new();
    let mut seen = 0;
    for line in golden.lines() {
        let fields: Vec<&str> = line.split(' ').collect();
        if fields[0] != direction {
            continue;
        }
        let (name, seq, bytes) = (
            fields[1],
            fields[2].parse::<u16>().unwrap(),
            unhex(fields[3]),
        );
        let results: Vec<_> = decoder.feed(&bytes).collect();
        assert_eq!(results.len(), 1, "{name}: one frame per golden line");
        let received = results
            .into_iter()
            .next()
            .unwrap()
            .expect("golden frame decodes");
        let (sample_name, sample) = &samples[seen];
        assert_eq!(*sample_name, name);
        assert_eq!(received.seq, seq);
        assert_eq!(received.missed, 0);
        assert_eq!(&received.message, sample, "{name}");
        seen += 1;
    }
    assert_eq!(seen, samples.len());
}

#[test]
fn golden_bytes_decode_to_the_samples() {
    decode_golden::<HostMessage>("host", &samples::host_messages());
    decode_golden::<ControllerMessage>("controller", &samples::controller_messages());
}

/// The frame of `Arm` (host variant 4) with seq 6, derived by hand from the framing rules with an
/// independent CRC-32C: checks the golden file is not just the encoder agreeing with itself.
#[test]
fn arm_frame_is_hand_derivable() {
    // raw = seq 6 LE (06 00), postcard variant index 4 (04), CRC-32C LE of [06 00 04].
    let crc = crc32c(&[0x06, 0x00, 0x04]);
    let mut raw = vec![0x06, 0x00, 0x04];
    raw.extend_from_slice(&crc.to_le_bytes());
    // COBS of raw, which contains one zero at index 1: [02 06] [len 06 04 crc..] then delimiter.
    let mut expected = vec![0x02, 0x06];
    let tail: Vec<u8> = raw[2..].to_vec();
    assert!(
        tail.iter().all(|&b| b != 0),
        "this derivation assumes a zero-free CRC"
    );
    expected.push(tail.len() as u8 + 1);
    expected.extend_from_slice(&tail);
    expected.push(0x00);
    let mut buf = [0u8; MAX_WIRE_FRAME_LEN];
    let len = encode_frame(6, &HostMessage::Arm, &mut buf).unwrap();
    assert_eq!(&buf[..len], &expected[..]);
}

/// Bitwise CRC-32C (reflected polynomial 0x82F63B78), independent of the `crc` crate.
fn crc32c(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0x82f6_3b78
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

#[test]
fn crc32c_reference_check_value() {
    // The standard check value of CRC-32C over "123456789".
    assert_eq!(crc32c(b"123456789"), 0xe306_9283);
}
