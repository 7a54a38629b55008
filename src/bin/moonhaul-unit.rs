//! `moonhaul-unit`: the per-robot daemon (see `moonhaul_deploy::daemon`).

use clap::Parser;

fn main() -> std::process::ExitCode {
    let args = moonhaul_deploy::daemon::DaemonArgs::parse();
    moonhaul_deploy::cli_support::init_tracing();
    let runtime = match moonhaul_deploy::cli_support::runtime() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("error: cannot start the async runtime: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    match runtime.block_on(moonhaul_deploy::daemon::run(args)) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!("{e:#}");
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
