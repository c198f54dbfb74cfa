//! Generates the phone2act.v1 types and service stubs with a vendored protoc, so no hand-installed
//! compiler is needed. A `PROTOC` variable still overrides.
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // tonic-prost-build prints no rerun line for .proto files; once any rerun line exists cargo stops
    // watching the package, so watch the proto folder ourselves (shared/spec/rust-build.md pitfall 1).
    println!("cargo:rerun-if-changed=phone2act");
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed=PROTOC");
    if std::env::var_os("PROTOC").is_none() {
        // SAFETY-free: build scripts are single threaded; set_var is unsafe in edition 2024 only for that reason.
        let protoc = protoc_bin_vendored::protoc_bin_path()?;
        #[allow(unsafe_code)]
        // SAFETY: the build script has no other threads that could read the environment concurrently.
        unsafe {
            std::env::set_var("PROTOC", protoc);
        }
    }
    let out_dir = PathBuf::from(std::env::var("OUT_DIR")?);
    let files = [
        "phone2act/v1/common.proto",
        "phone2act/v1/teleop.proto",
        "phone2act/v1/policy.proto",
        "phone2act/v1/episodes.proto",
        "phone2act/v1/system.proto",
        "phone2act/v1/bridge.proto",
        "phone2act/v1/cameras.proto",
        "phone2act/v1/scene.proto",
    ];
    tonic_prost_build::configure()
        .file_descriptor_set_path(out_dir.join("phone2act_v1_descriptor.bin"))
        .compile_protos(&files, &["."])?;
    Ok(())
}
