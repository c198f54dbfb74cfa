//! Robot bridges behind one `Bridge` trait: the simulated SO-101 arm, the Dobot CR5 over TCP, the SO-101 over
//! a Feetech servo bus, and remote bridges attached over gRPC; plus the protocol emulators (Dobot controller,
//! Feetech bus) that the tests and demos run against.
