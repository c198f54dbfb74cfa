//! `phone2act replay-log`: re-runs the pure core on flight logs and checks that every command and gate
//! decision comes out identical, naming the first input where one does not.

use phone2act_server::Config;
use phone2act_server::flight_log::{Verdict, replay_file};
use std::path::{Path, PathBuf};

/// The command: every file is replayed; the first difference of each is printed. Fails if any differs.
pub(crate) fn run(files: &[PathBuf], config: Option<&Path>) -> anyhow::Result<()> {
    let config = config.map(Config::load).transpose()?;
    let mut differing = 0;
    for path in files {
        let (verdict, ending) = replay_file(path, config.as_ref())?;
        match verdict {
            Verdict::Identical(c) => {
                crate::write_stdout_line(format_args!(
                    "{}: {} inputs replayed, {} commands, {} gate decisions, {} refusals: identical; {ending}",
                    path.display(),
                    c.inputs,
                    c.commands,
                    c.decisions,
                    c.refused
                ));
            }
            Verdict::Differs(d) => {
                differing += 1;
                crate::write_stdout_line(format_args!("{}: first difference at {d}", path.display()));
            }
        }
    }
    if differing > 0 {
        anyhow::bail!(
            "{differing} of {} flight log(s) replayed differently",
            files.len()
        );
    }
    Ok(())
}
