//! The `tyndall` binary (the same code as the Python package's `tyndall` command).
fn main() {
    std::process::exit(tyndall_cli::run(std::env::args_os()));
}
