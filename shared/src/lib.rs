//! Wire protocol between the MLSSS booth controller (firmware) and the host.
#![no_std]

/// Version of the wire protocol; bumped on any incompatible change.
pub const PROTOCOL_VERSION: u16 = 1;
