//! The command line (clap): one file per subcommand.

/// Runs the command line; returns the process exit code.
pub fn main() -> i32 {
    0
}
