use clap::Parser;
use std::process::ExitCode;

/// Exit code for bad input and failures; 1 is reserved for "ran fine, quality not met".
const EXIT_ERROR: u8 = 2;
/// A compile whose result is past a lossy pass's hard limit: nothing was written.
const EXIT_QUALITY: u8 = 1;

fn main() -> ExitCode {
    let cli = match pdi_compile::cli::Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) if !e.use_stderr() => e.exit(), // --help, --version
        Err(e) => {
            // One line, like every other error: clap's first line, then where the usage is.
            let text = e.render().to_string();
            let first = text.lines().find(|l| !l.trim().is_empty()).unwrap_or("error: bad arguments");
            eprintln!("{}; see --help", first.trim_end());
            return ExitCode::from(EXIT_ERROR);
        }
    };
    // A panic is a bug, but the user still gets one line and exit 2, not a backtrace.
    std::panic::set_hook(Box::new(|_| {}));
    match std::panic::catch_unwind(|| pdi_compile::cli::run(cli)) {
        Ok(Ok(code)) => ExitCode::from(code),
        Ok(Err(e)) => {
            eprintln!("error: {}", format!("{e:#}").replace('\n', " "));
            // A model past a pass's hard limit is a quality failure, like a failed gate.
            ExitCode::from(if pdi_compile::pipeline::is_quality_failure(&e) { EXIT_QUALITY } else { EXIT_ERROR })
        }
        Err(p) => {
            let msg = p.downcast_ref::<String>().cloned().or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string())).unwrap_or_default();
            eprintln!("error: internal error ({msg}); please report it with the input that caused it");
            ExitCode::from(EXIT_ERROR)
        }
    }
}
