//! `moonhaul sim handovers`: flies seeded missions through the deployed stack (onboard tick,
//! phase gate, clamp; the scripted controller or the bundled policies) and writes where each
//! handed over to transport and to place, for training episodes that start there
//! ([`moonhaul_sim::handover`]). Only missions that completed are kept: a hand-over of a
//! mission that later failed is a start the expert itself could not finish from.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use indicatif::ProgressBar;
use moonhaul_coord::{GateConfig, SyncConfig};
use moonhaul_core::atomic_file;
use moonhaul_core::overwrite::RunInputs;
use moonhaul_core::scripted::MissionPlan;
use moonhaul_core::state::Phase;
use moonhaul_core::task_config::TaskConfig;
use moonhaul_deploy::cli_support::{load_policy, policy_file};
use moonhaul_deploy::tick::{Controller, PhasePolicies};
use moonhaul_deploy::unit_config::UnitConfig;
use moonhaul_sim::handover::HandOverFile;
use moonhaul_sim::{PayloadKind, SceneModel, SimConfig};

use crate::eval::deployed::{self, Stack};
use crate::eval::rollout::Episodes;

/// What flies the missions whose hand-overs are captured.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Flier {
    Scripted,
    Learned,
}

#[derive(Debug, clap::Args)]
pub struct HandoverArgs {
    /// Payloads to fly, comma-separated: shipped ones or generated members (`gen<i>`); a
    /// training world rebuilds the capture's world, so payload files are not taken. The sledge
    /// is left out by default: it is the payload no training sees.
    #[arg(long, value_delimiter = ',', default_value = "box,bricks")]
    payload: Vec<PayloadKind>,
    /// Missions per payload of `--payload`, 1 to 10000.
    #[arg(long, default_value_t = 16)]
    episodes: usize,
    /// Missions per member of the sim config's generated payload family, 0 to 10000 (0: none).
    #[arg(long, default_value_t = 4)]
    generated_episodes: usize,
    /// Mission k of a payload flies the world of the k-th stream of this seed.
    #[arg(long, default_value_t = 7)]
    seed: u64,
    #[arg(long, value_enum, default_value = "scripted")]
    controller: Flier,
    /// Folder of the phase policies (`learned`).
    #[arg(long, default_value = "assets/policies")]
    policies: PathBuf,
    /// The hand-over file to write (JSON).
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Replace an existing `--out` (never an input of the run).
    #[arg(long)]
    force: bool,
    /// Simulator threads (0: one per core).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    #[arg(long, default_value = "configs/sim.toml")]
    sim: PathBuf,
    #[arg(long, default_value = "configs/tasks.toml")]
    tasks: PathBuf,
    #[arg(long, default_value = "configs/sync.toml")]
    sync: PathBuf,
    #[arg(long, default_value = "configs/gate.toml")]
    gate: PathBuf,
    #[arg(long, default_value = "configs/unit.toml")]
    unit: PathBuf,
    #[arg(long, default_value = "configs/mission.toml")]
    mission: PathBuf,
}

pub fn run(args: HandoverArgs) -> Result<()> {
    if !(1..=10_000).contains(&args.episodes) {
        bail!("--episodes {}: must be 1 to 10000", args.episodes);
    }
    if args.generated_episodes > 10_000 {
        bail!(
            "--generated-episodes {}: must be 0 to 10000",
            args.generated_episodes
        );
    }
    if args.threads > 1024 {
        bail!("--threads {}: at most 1024", args.threads);
    }
    let mut inputs = RunInputs::new();
    for (role, path) in [
        ("--sim", &args.sim),
        ("--tasks", &args.tasks),
        ("--sync", &args.sync),
        ("--gate", &args.gate),
        ("--unit", &args.unit),
        ("--mission", &args.mission),
    ] {
        inputs.add(role, path);
    }
    inputs.check_output("--out", &args.out, args.force)?;
    let scene = SceneModel::new(SimConfig::load(&args.sim)?).context("building the scene")?;
    let stack = Stack {
        team: UnitConfig::from_file(&args.unit)?.team_settings(),
        gate: GateConfig::from_file(&args.gate)?,
        sync: SyncConfig::from_file(&args.sync)?,
        tasks: TaskConfig::load(&args.tasks)?,
    };
    let plan = MissionPlan::load(&args.mission)?;
    let policies = match args.controller {
        Flier::Scripted => None,
        Flier::Learned => Some(load_policies(&args.policies)?),
    };
    let controller = || -> Result<Controller> {
        Ok(match &policies {
            None => Controller::Scripted(plan),
            Some(p) => Controller::Learned(Box::new(PhasePolicies {
                lift: p[0].clone(),
                transport: p[1].clone(),
                place: p[2].clone(),
            })),
        })
    };
    for &payload in &args.payload {
        scene
            .payload(payload)
            .with_context(|| format!("--payload {}", scene.payload_name(payload)))?;
    }
    let family = scene.config.randomization.generated_payloads.count;
    let flights = args
        .payload
        .iter()
        .map(|&p| (p, args.episodes))
        .chain((0..family).map(|i| (PayloadKind::Generated(i), args.generated_episodes)))
        .filter(|&(_, count)| count > 0);
    let mut handovers = Vec::new();
    for (payload, count) in flights {
        let run = Episodes {
            payload,
            randomize: true,
            count,
            seed: args.seed,
            threads: args.threads,
        };
        let bar = ProgressBar::new(count as u64);
        let missions = deployed::missions(&scene, &stack, &controller, run, true, &bar)
            .with_context(|| format!("flying {}", scene.payload_name(payload)))?;
        bar.finish_and_clear();
        let completed = missions.iter().filter(|m| m.completed).count();
        eprintln!(
            "{}: {completed}/{count} missions completed; their hand-overs kept",
            scene.payload_name(payload),
        );
        handovers.extend(
            missions
                .into_iter()
                .filter(|m| m.completed)
                .flat_map(|m| m.handovers),
        );
    }
    let count = |phase| handovers.iter().filter(|h| h.phase == phase).count();
    let (transport, place) = (count(Phase::Transport), count(Phase::Place));
    if transport == 0 || place == 0 {
        bail!(
            "no mission completed: nothing to write to {}",
            args.out.display()
        );
    }
    write(&args.out, &HandOverFile::new(handovers))?;
    println!(
        "wrote {}: {transport} hand-overs into transport, {place} into place",
        args.out.display()
    );
    Ok(())
}

fn load_policies(folder: &Path) -> Result<[moonhaul_core::policy::Policy; 3]> {
    let load = |phase| load_policy(&policy_file(folder, phase), phase);
    Ok([
        load(Phase::Lift)?,
        load(Phase::Transport)?,
        load(Phase::Place)?,
    ])
}

fn write(path: &Path, file: &HandOverFile) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let json = serde_json::to_vec(file).context("encoding the hand-overs")?;
    atomic_file::write(path, &json).with_context(|| format!("writing {}", path.display()))
}
