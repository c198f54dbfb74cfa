//! Feetech STS3215 servo bus (the SO-101's motors): the packet protocol, a serial-port client, and (with the
//! `emulators` feature) an emulated bus on a pseudo-terminal for tests and benchmarks.

pub mod bus;
#[cfg(feature = "emulators")]
pub mod emulator;
pub mod protocol;

pub use bus::{BusError, BusStats, FeetechBus, ServoReply};
#[cfg(feature = "emulators")]
pub use emulator::FeetechEmulator;
