//! `moonhaul`: the operator's umbrella CLI. It never links libtorch (training lives in
//! `moonhaul-train`); everything here runs on the pure-Rust core.

/// `println!` that returns an error (a closed pipe, a full disk) instead of panicking, so
/// `moonhaul … | head` ends cleanly.
macro_rules! outln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        writeln!(std::io::stdout().lock(), $($arg)*)
            .map_err(|e| anyhow::anyhow!("cannot write to stdout: {e}"))
    }};
}

mod can_cmd;
mod eval;
mod eval_cmd;
mod handover_cmd;
mod keys_cmd;
mod log_cmd;
mod log_ros2;
mod mission;
mod payload_arg;
mod policy_cmd;
mod sim_cmd;
mod urdf_cmd;

use std::io::Write as _;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "moonhaul",
    version,
    about = "Cooperative lunar cargo transport: tools and missions"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Inspect URDF robot models: kinematic tree, limits, forward kinematics.
    #[command(subcommand)]
    Urdf(urdf_cmd::UrdfCommand),
    /// Inspect onboard policy files (safetensors).
    #[command(subcommand)]
    Policy(policy_cmd::PolicyCommand),
    /// CAN bus tools: emulate a unit's CiA 402 drives and record the master's traffic.
    #[command(subcommand)]
    Can(can_cmd::CanCommand),
    /// Simulator tools: run the scripted lift-transport-place mission (CSV + PNG), benchmark.
    #[command(subcommand)]
    Sim(sim_cmd::SimCommand),
    /// Evaluate the phase policies against the paper's simulation results, beside the scripted
    /// IK controller: seeded, randomized episodes of every case and payload.
    Eval(eval_cmd::EvalArgs),
    /// Mission logs: the paper's hardware metrics of a mission directory's ground truth; logs
    /// as ROS 2 bags.
    #[command(subcommand)]
    Log(log_cmd::LogCommand),
    /// Team key files that authenticate peer and operator messages: generate one per team (mode
    /// 0600, kept outside the repository, e.g. ~/.config/moonhaul/<team>.keys.toml).
    #[command(subcommand)]
    Keys(keys_cmd::KeysCommand),
    /// Missions: operator start/stop/status over zenoh, simulated missions of real processes.
    #[command(subcommand)]
    Mission(mission::MissionCommand),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Urdf(cmd) => urdf_cmd::run(cmd),
        Command::Policy(cmd) => policy_cmd::run(cmd),
        Command::Can(cmd) => can_cmd::run(cmd),
        Command::Sim(cmd) => sim_cmd::run(cmd),
        Command::Eval(args) => eval_cmd::run(args),
        Command::Log(cmd) => log_cmd::run(cmd),
        Command::Keys(cmd) => keys_cmd::run(cmd),
        Command::Mission(cmd) => mission::run(cmd),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(err) => {
            // Nothing is left to tell if stderr is gone too.
            let _ = writeln!(std::io::stderr().lock(), "error: {err:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
