//! Feetech STS3215 servo bus (the SO-101's motors): the packet protocol, a serial-port client, and an emulated
//! bus on a pseudo-terminal for tests and demos.

pub mod bus;
pub mod emulator;
pub mod protocol;

pub use bus::{BusError, BusStats, FeetechBus};
pub use emulator::FeetechEmulator;
