//! SO-101 bridge.
