//! A command's results on standard output, the way Unix tools print them: when stdout is a closed pipe
//! (`dsrl-admin build --status | head`), the process ends quietly with exit status 141, as a shell reports SIGPIPE,
//! where `println!` would panic. The binaries print through [`out!`](crate::out).

/// `println!` that ends the process quietly when stdout is a closed pipe (see the module).
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => {
        $crate::output::emit(format_args!($($arg)*))
    };
}

/// One line of `args` on stdout; a closed pipe ends the process with 141, any other write error with
/// [`FAILURE`](crate::error::exit::FAILURE) and the error on stderr.
pub fn emit(args: std::fmt::Arguments<'_>) {
    use std::io::Write;
    if let Err(e) = writeln!(std::io::stdout().lock(), "{args}") {
        if e.kind() == std::io::ErrorKind::BrokenPipe {
            std::process::exit(141);
        }
        let program = std::env::args().next().unwrap_or_default();
        eprintln!("{program}: writing to stdout: {e}");
        std::process::exit(i32::from(crate::error::exit::FAILURE));
    }
}
