//! `moonhaul mission`: the operator's console (`start`, `stop`, `status`) and simulated
//! missions of real processes (`sim`, and the `world` process it starts).

pub mod operator;
pub mod sim;
pub mod world;

use anyhow::{Context, Result};

#[derive(clap::Subcommand)]
pub enum MissionCommand {
    /// Start a mission: listen to the units, then send a signed start with a new mission number.
    Start(operator::ConsoleArgs),
    /// Stop the team at once (a signed operator stop; every unit holds).
    Stop(operator::ConsoleArgs),
    /// Each unit's phase, announced stop, pending change and base pose, as heard now.
    Status(operator::ConsoleArgs),
    /// A simulated mission of real processes: one world, one moonhaul-unit per unit, over
    /// zenoh on loopback; then the summary of the ground truth.
    Sim(sim::SimArgs),
    /// The simulated world alone (what `mission sim` starts): physics, the units' sim-backed
    /// drives over zenoh, the ground-truth log.
    World(world::WorldArgs),
}

pub fn run(cmd: MissionCommand) -> Result<()> {
    let runtime = moonhaul_deploy::cli_support::runtime().context("starting the async runtime")?;
    moonhaul_deploy::cli_support::init_tracing();
    runtime.block_on(async move {
        match cmd {
            MissionCommand::Start(args) => operator::run("start", &args).await,
            MissionCommand::Stop(args) => operator::run("stop", &args).await,
            MissionCommand::Status(args) => operator::run("status", &args).await,
            MissionCommand::World(args) => world::run(args).await,
            MissionCommand::Sim(args) => {
                let out = args.out.clone();
                let runs = sim::run(args).await?;
                let failed = runs
                    .iter()
                    .filter(|r| !r.world_ok || r.units_ok.iter().any(|ok| !ok))
                    .count();
                crate::log_cmd::summarize(&out, false)?;
                if failed > 0 {
                    eprintln!(
                        "mission sim: {failed} of {} trials had a process exit with an error \
                         (see the *.log files)",
                        runs.len()
                    );
                }
                Ok(())
            }
        }
    })
}
