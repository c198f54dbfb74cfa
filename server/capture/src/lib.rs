//! phone2act cameras, the capture side of recording: a thread per camera publishing into a latest-frame slot
//! that also keeps its recent frames by capture time ([`camera`], [`timeline`]), test-pattern and rendered
//! sources, FFmpeg devices ([`av::device`]), JPEG for frames on the wire ([`jpeg`]), background thread
//! priority ([`priority`]), and the H.264 encoder of the operator's live video ([`av::live`]). FFmpeg is
//! reached only through [`av`]. The recorder (`phone2act-recorder`) reads the slots; nothing here writes a
//! dataset.

pub mod av;
pub mod camera;
pub mod jpeg;
pub mod priority;
pub mod timeline;
