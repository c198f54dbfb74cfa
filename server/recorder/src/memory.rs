//! Keeping a long-running recorder's resident memory flat under glibc's allocator.
//!
//! Every episode starts and ends one encoder thread per camera, and SVT-AV1 starts a dozen threads of its
//! own per encoder. glibc gives threads separate malloc arenas (up to 8 per core) and keeps what they free
//! for reuse, so each episode's encoder buffers could land in yet another arena: a soak of 20 s episodes
//! grew from 105 to 260 MB before levelling off. Capping the arenas and handing freed pages back after
//! each episode keeps it flat. Both are no-ops on other C libraries.

/// Caps glibc's malloc arenas for the whole process. Call at the start of `main`, before threads start
/// (the cap applies to arenas created afterwards). Respects a `MALLOC_ARENA_MAX` the user set.
#[allow(unsafe_code)]
pub fn limit_malloc_arenas() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    if std::env::var_os("MALLOC_ARENA_MAX").is_none() {
        // Two arenas: the control path (tokio workers) and the recorder's threads rarely allocate at the
        // same instant; more arenas only multiply what each keeps cached.
        // SAFETY: mallopt only changes allocator parameters; it is thread-safe in glibc.
        unsafe {
            libc::mallopt(libc::M_ARENA_MAX, 2);
        }
    }
}

/// Returns freed heap pages to the system. Called after an episode is saved or discarded, when its
/// encoders' buffers have just been freed; takes about a millisecond.
#[allow(unsafe_code)]
pub fn release_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim is thread-safe in glibc and only releases memory that is free.
    unsafe {
        libc::malloc_trim(0);
    }
}
