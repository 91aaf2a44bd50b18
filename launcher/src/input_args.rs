//! The input options every command that reads files takes.

use lung_model::input::ReadLimits;

/// Size limit and special-file permission for the files a command reads.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct InputArgs {
    /// Largest input file read, MiB (defaults: 2048 for meshes, 256 for tables such as PV curves and
    /// landmark files). A larger file is refused before anything is read.
    #[arg(long, value_name = "MIB", value_parser = clap::value_parser!(u64).range(1..=65536))]
    pub max_input_mib: Option<u64>,
    /// Also read devices, pipes and sockets (at most the size limit). Without it such a path is
    /// refused at once: a wrong path like /dev/zero must not hang the command.
    #[arg(long)]
    pub allow_special: bool,
}

impl InputArgs {
    /// `base` with these options applied.
    pub fn limits(&self, base: ReadLimits) -> ReadLimits {
        base.with(self.max_input_mib, self.allow_special)
    }
}
