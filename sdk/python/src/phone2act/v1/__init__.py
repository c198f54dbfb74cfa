"""Generated protobuf and gRPC modules of the `phone2act.v1` API (made at build time from proto/)."""
