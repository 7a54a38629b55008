//! `moonhaul eval`: the paper's simulation results table, measured — the bundled phase
//! policies (learned) beside the scripted IK controller (a model-based baseline the paper
//! lacks), over seeded, randomized episodes of every case and payload. Metrics are defined in
//! [`crate::eval::metrics`]; `--out` writes every episode's rows so they can be recomputed.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use moonhaul_coord::{GateConfig, SyncConfig};
use moonhaul_core::state::Phase;
use moonhaul_sim::scripted::MissionPlan;
use moonhaul_sim::task::{PhaseTask, TaskConfig};
use moonhaul_sim::{PayloadKind, SceneModel, SimConfig};
use serde_json::{json, Map, Value};

use crate::eval::deployed;
use crate::eval::episode::{read_csv, write_csv, EpisodeRow};
use crate::eval::metrics::{self, lift_summary, place_summary, transport_summary};
use crate::eval::plot;
use crate::eval::progress::Progress;
use crate::eval::rollout::{self, Case, Episodes, ScriptedSegments};
use crate::payload_arg::{self, PayloadArg};
use moonhaul_core::action::ActionMap;
use moonhaul_core::atomic_file;
use moonhaul_core::overwrite::{check_output_folder, RunInputs};
use moonhaul_core::policy::Policy;
use moonhaul_deploy::cli_support::policy_file;
use moonhaul_deploy::tick::{Controller, PhasePolicies};
use moonhaul_deploy::unit_config::UnitConfig;

#[derive(clap::Args)]
pub struct EvalArgs {
    /// Folder holding lift.safetensors, transport.safetensors and place.safetensors.
    #[arg(long, default_value = "assets/policies")]
    policies: PathBuf,
    /// Payloads to evaluate (box, bricks, sledge, gen<i> of the generated training family, or
    /// payload URDF paths, which name their outputs by file stem), comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "box,bricks,sledge")]
    payload: Vec<PayloadArg>,
    /// Cases to run (lift-0.3, lift-0.5, lift-0.75, transport, place), comma-separated; only
    /// the policies they need are loaded.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "lift-0.3,lift-0.5,lift-0.75,transport,place"
    )]
    cases: Vec<String>,
    /// Seeded episodes per case and payload, 1 to 10000.
    #[arg(long, default_value_t = 100)]
    episodes: usize,
    /// Seed of the first episode's world; episode k uses the k-th stream of it.
    #[arg(long, default_value_t = 1000)]
    seed: u64,
    /// Nominal world: flat ground, mid-range friction, no command noise (shows which figures
    /// the terrain bounds).
    #[arg(long)]
    no_randomization: bool,
    /// Skip the scripted-controller baseline.
    #[arg(long)]
    no_scripted: bool,
    /// Skip the learned policies (no policy file is loaded): only the scripted controller's
    /// rows, e.g. to evaluate the expert before any policy of this build's layout exists.
    #[arg(long, conflicts_with = "no_scripted")]
    no_learned: bool,
    /// Skip the deployed stack (whole missions with the phase gate and the synchronization
    /// clamp in the loop; run when every case is).
    #[arg(long)]
    no_deployed: bool,
    #[arg(long, default_value = "configs/gate.toml")]
    gate: PathBuf,
    #[arg(long, default_value = "configs/sync.toml")]
    sync: PathBuf,
    /// The unit config whose team settings (peer staleness) the deployed stack's units use.
    #[arg(long, default_value = "configs/unit.toml")]
    unit: PathBuf,
    /// Write every episode's rows to DIR/<payload>/<case>/<episode>.csv (scripted ones under
    /// DIR/scripted/): a new or empty folder, unless `--force`; never over an input.
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Write into a `--out` folder that holds files already (an earlier run's).
    #[arg(long, requires = "out")]
    force: bool,
    /// Print one JSON line instead of the table.
    #[arg(long)]
    json: bool,
    /// Simulate nothing: recompute the metrics from the CSVs an earlier `--out DIR` wrote.
    #[arg(long, value_name = "DIR", conflicts_with = "out")]
    recompute: Option<PathBuf>,
    /// Simulator threads (0: one per core).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    #[arg(long, default_value = "configs/sim.toml")]
    sim: PathBuf,
    #[arg(long, default_value = "configs/tasks.toml")]
    tasks: PathBuf,
    /// The scripted controller's mission plan.
    #[arg(long, default_value = "configs/mission.toml")]
    mission: PathBuf,
}

impl EvalArgs {
    /// The files an evaluation reads: none of its outputs may replace one.
    fn inputs(&self) -> RunInputs {
        let mut inputs = RunInputs::new();
        for phase in [Phase::Lift, Phase::Transport, Phase::Place] {
            inputs.add(
                format!("{phase} policy"),
                policy_file(&self.policies, phase),
            );
        }
        for name in ["lift", "transport", "place", "mission"] {
            inputs.add(
                "training curve",
                self.policies.join(format!("{name}.metrics.csv")),
            );
        }
        inputs
            .add("gate config", &self.gate)
            .add("sync config", &self.sync)
            .add("unit config", &self.unit)
            .add("simulator config", &self.sim)
            .add("task config", &self.tasks)
            .add("mission plan", &self.mission);
        for payload in &self.payload {
            if let PayloadArg::File(path) = payload {
                inputs.add("payload", path);
            }
        }
        inputs
    }

    fn episodes_of(&self, payload: PayloadKind) -> Episodes {
        Episodes {
            payload,
            randomize: !self.no_randomization,
            count: self.episodes,
            seed: self.seed,
            threads: self.threads,
        }
    }
}

/// The paper's simulation results (Sec. VIII-A): (case, metric, value). Steady lift tilt is
/// reported as a bound (< 2.5°).
const PAPER: [(&str, &str, f64); 13] = [
    ("lift-0.3", "final_height_error_mm", 5.9),
    ("lift-0.3", "peak_tilt_deg", 17.9),
    ("lift-0.3", "steady_tilt_deg", 2.5),
    ("lift-0.5", "final_height_error_mm", 17.4),
    ("lift-0.5", "peak_tilt_deg", 22.8),
    ("lift-0.75", "final_height_error_mm", 36.0),
    ("lift-0.75", "peak_tilt_deg", 25.4),
    ("transport", "rms_velocity_error_mps", 0.023),
    ("transport", "max_height_deviation_mm", 1.58),
    ("place", "final_height_error_mm", 13.3),
    ("place", "touchdown_speed_mps", 0.030),
    ("place", "peak_tilt_deg", 6.0),
    ("place", "steady_tilt_deg", 0.6),
];

fn paper_value(case: &str, metric: &str) -> Option<f64> {
    PAPER
        .iter()
        .find(|(c, m, _)| *c == case && *m == metric)
        .map(|(_, _, v)| *v)
}

/// The summary of one case's episodes: per metric `{"mean", "sd"}`, and `"paper"` where the
/// paper reports the metric (so a reader of `--json`, such as `cargo xtask train-all`'s lift
/// selection, compares against the same figures as the table).
fn summarize(case: Case, episodes: &[Vec<EpisodeRow>]) -> Result<Value> {
    let mut summary = summarize_metrics(case, episodes)?;
    if let Value::Object(metrics) = &mut summary {
        for (metric, value) in metrics.iter_mut() {
            if let (Some(paper), Value::Object(stats)) = (paper_value(&case.name(), metric), value)
            {
                stats.insert("paper".into(), json!(paper));
            }
        }
    }
    Ok(summary)
}

fn summarize_metrics(case: Case, episodes: &[Vec<EpisodeRow>]) -> Result<Value> {
    Ok(match case.phase {
        Phase::Lift => lift_summary(
            &episodes
                .iter()
                .map(|rows| metrics::lift(rows))
                .collect::<Result<Vec<_>, _>>()?,
        ),
        Phase::Transport => transport_summary(
            &episodes
                .iter()
                .map(|rows| metrics::transport(rows))
                .collect::<Result<Vec<_>, _>>()?,
        ),
        Phase::Place | Phase::Idle => place_summary(
            &episodes
                .iter()
                .map(|rows| metrics::place(rows))
                .collect::<Result<Vec<_>, _>>()?,
        ),
    })
}

/// `--out`'s episode CSVs in `dir`, none over an input of the run (`inputs`).
fn write_episodes(inputs: &RunInputs, dir: &Path, episodes: &[Vec<EpisodeRow>]) -> Result<()> {
    for (k, rows) in episodes.iter().enumerate() {
        let path = dir.join(format!("{k:03}.csv"));
        inputs.check_output("--out", &path, true)?;
        write_csv(&path, rows)?;
    }
    Ok(())
}

/// The JSON shape of one payload: `{"episodes":N,"lift":{"0.3":M,...},"transport":M,"place":M}`.
fn payload_json(episodes: usize, cases: &[(Case, Value)]) -> Value {
    let mut lift = Map::new();
    let mut out = Map::new();
    out.insert("episodes".into(), json!(episodes));
    for (case, summary) in cases {
        match case.goal_height_m {
            Some(h) => {
                lift.insert(format!("{h}"), summary.clone());
            }
            None => {
                out.insert(case.phase.name().into(), summary.clone());
            }
        }
    }
    out.insert("lift".into(), Value::Object(lift));
    Value::Object(out)
}

/// Every episode CSV of `dir`, in file-name order.
fn read_episodes(dir: &Path) -> Result<Vec<Vec<EpisodeRow>>> {
    let mut files = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .map(|e| e.map(|e| e.path()))
        .collect::<Result<Vec<_>, _>>()
        .with_context(|| format!("reading {}", dir.display()))?;
    files.retain(|p| p.extension().is_some_and(|e| e == "csv"));
    files.sort();
    if files.is_empty() {
        bail!("{}: no episode CSVs", dir.display());
    }
    files.iter().map(|f| read_csv(f)).collect()
}

/// `--recompute DIR`: the JSON report from the CSVs alone.
fn recompute(dir: &Path, payloads: &[PayloadArg]) -> Result<()> {
    let mut report = Map::new();
    for payload in payloads {
        let name = payload.name();
        let mut cases = Vec::new();
        let mut episodes = 0;
        for case in Case::ALL {
            let rows = read_episodes(&dir.join(&name).join(case.name()))?;
            episodes = rows.len();
            cases.push((case, summarize(case, &rows)?));
        }
        report.insert(name, payload_json(episodes, &cases));
    }
    outln!("{}", Value::Object(report))
}

pub fn run(args: EvalArgs) -> Result<()> {
    if let Some(dir) = &args.recompute {
        return recompute(dir, &args.payload);
    }
    if !(1..=10_000).contains(&args.episodes) {
        bail!("--episodes {}: must be 1 to 10000", args.episodes);
    }
    if args.threads > 1024 {
        bail!("--threads {}: at most 1024", args.threads);
    }
    if let Some(out) = &args.out {
        check_output_folder("--out", out, args.force)?;
    }
    let sim = SimConfig::load(&args.sim)?;
    let tasks = TaskConfig::load(&args.tasks)?;
    let sync = SyncConfig::from_file(&args.sync)?;
    let plan = MissionPlan::load(&args.mission)?;
    let mut scene = SceneModel::new(sim).context("building the scene")?;
    // Every payload file is loaded and grasp-solved before any episode runs, so a bad one
    // fails at once; a scene holds one custom payload, so each file's model goes back in turn.
    let mut payloads = Vec::new();
    for arg in &args.payload {
        let kind = payload_arg::resolve(&mut scene, arg)?;
        let name = scene.payload_name(kind);
        if payloads.iter().any(|(_, n, _)| *n == name) {
            bail!("--payload: two payloads are named {name:?}; their outputs would collide");
        }
        payloads.push((kind, name, scene.payloads.get(&kind).cloned()));
    }
    let randomize = !args.no_randomization;
    let mut cases = Vec::new();
    for name in &args.cases {
        match Case::ALL.iter().find(|c| c.name() == *name) {
            Some(case) => cases.push(*case),
            None => bail!(
                "--cases {name:?}: unknown case (expected lift-0.3, lift-0.5, lift-0.75, \
                 transport or place)"
            ),
        }
    }
    let mut policies = Vec::new();
    for phase in [Phase::Lift, Phase::Transport, Phase::Place] {
        if args.no_learned || !cases.iter().any(|c| c.phase == phase) {
            continue;
        }
        let path = policy_file(&args.policies, phase);
        let mut task = PhaseTask::new(phase, tasks, sync, &scene)?;
        // The place metrics' steady window is an episode's last second. Cut at the training
        // episode's end, it held the last ticks before a late release (and some placements still
        // held); the scripted controller's place segment runs `after_release_s` past its
        // release. So a learned placement runs that much past the training episode's end.
        if phase == Phase::Place {
            task = task.with_time_limit_s(tasks.duration_s(phase) + plan.after_release_s);
        }
        let policy = rollout::load_policy(&path, phase)?;
        // The episodes bound increments by the tasks' map; a policy trained with other steps
        // would be evaluated on a map it was not trained on.
        let map = ActionMap::of_policy(&policy)?;
        // The file stores the steps as f32.
        let same = |a: f64, b: f64| a as f32 == b as f32;
        if !map
            .step
            .iter()
            .zip(&task.action_map().step)
            .all(|(a, b)| same(*a, *b))
        {
            bail!(
                "policy {} was trained with action steps {:?}; {} [action] gives {:?}",
                path.display(),
                map.step,
                args.tasks.display(),
                task.action_map().step
            );
        }
        policies.push((phase, task, policy));
    }

    let every_case = Case::ALL.iter().all(|c| cases.contains(c));
    let stack = if args.no_deployed || !every_case {
        None
    } else {
        let unit = UnitConfig::from_file(&args.unit)?;
        Some(deployed::Stack {
            team: unit.team_settings(),
            gate: GateConfig::from_file(&args.gate)?,
            sync,
            tasks,
        })
    };
    let mut report = Map::new();
    let mut table = String::new();
    let mut rollouts: Vec<(Phase, Vec<EpisodeRow>)> = Vec::new();
    let scripted_runs = if args.no_scripted {
        0
    } else {
        scripted_missions(&cases).len()
    };
    let deployed_runs = match &stack {
        Some(_) if args.no_scripted || args.no_learned => 1,
        Some(_) => 2,
        None => 0,
    };
    let learned_runs = if args.no_learned { 0 } else { cases.len() };
    let mut progress =
        Progress::new(payloads.len() * (learned_runs + scripted_runs + deployed_runs));
    for (payload, name, model) in &payloads {
        let payload = *payload;
        if let Some(model) = model {
            scene.payloads.insert(payload, model.clone());
        }
        let mut learned = Vec::new();
        for &case in cases.iter().filter(|_| !args.no_learned) {
            let (_, task, policy) = policies
                .iter()
                .find(|(p, ..)| *p == case.phase)
                .context("every phase has a policy")?;
            let run = progress.start(
                format!("{name} {} learned", case.name()),
                args.episodes,
                "episodes",
                task.max_steps(),
                "steps",
            );
            let episodes = rollout::learned(
                &scene,
                task,
                policy,
                case,
                args.episodes_of(payload),
                run.bar(),
            )
            .with_context(|| format!("{name} {}", case.name()))?;
            run.finish();
            if let Some(out) = &args.out {
                write_episodes(&args.inputs(), &out.join(name).join(case.name()), &episodes)?;
                // The first payload's first episode of each phase's first case is its figure.
                if !rollouts.iter().any(|(p, _)| *p == case.phase) {
                    if let Some(rows) = episodes.first() {
                        rollouts.push((case.phase, rows.clone()));
                    }
                }
            }
            learned.push((case, summarize(case, &episodes)?));
        }
        let scripted = if args.no_scripted {
            None
        } else {
            Some(scripted_cases(
                &scene,
                &plan,
                payload,
                &cases,
                &args,
                &mut progress,
            )?)
        };
        let (learned_deployed, scripted_deployed) = match &stack {
            Some(stack) => {
                let learned_policies = || -> Result<Controller> {
                    let find = |phase: Phase| -> Result<Policy> {
                        policies
                            .iter()
                            .find(|(p, ..)| *p == phase)
                            .map(|(.., policy)| policy.clone())
                            .with_context(|| format!("the deployed stack needs a {phase} policy"))
                    };
                    Ok(Controller::Learned(Box::new(PhasePolicies {
                        lift: find(Phase::Lift)?,
                        transport: find(Phase::Transport)?,
                        place: find(Phase::Place)?,
                    })))
                };
                let learned = if args.no_learned {
                    None
                } else {
                    Some(deployed_cases(
                        &scene,
                        stack,
                        &learned_policies,
                        payload,
                        &args,
                        "",
                        &mut progress,
                    )?)
                };
                let scripted = if args.no_scripted {
                    None
                } else {
                    let controller = || Ok(Controller::Scripted(plan));
                    Some(deployed_cases(
                        &scene,
                        stack,
                        &controller,
                        payload,
                        &args,
                        "scripted",
                        &mut progress,
                    )?)
                };
                (learned, scripted)
            }
            None => (None, None),
        };
        let mut entry = payload_json(args.episodes, &learned);
        if let Value::Object(map) = &mut entry {
            if let Some(scripted) = &scripted {
                let mut s = payload_json(args.episodes, scripted);
                if let (Value::Object(s), Some(d)) = (&mut s, &scripted_deployed) {
                    s.insert("deployed".into(), deployed_json(args.episodes, d));
                }
                map.insert("scripted".into(), s);
            }
            if let Some(d) = &learned_deployed {
                map.insert(
                    "learned".into(),
                    json!({ "deployed": deployed_json(args.episodes, d) }),
                );
            }
        }
        write_table(
            &mut table,
            name,
            args.episodes,
            randomize,
            &learned,
            scripted.as_deref(),
            learned_deployed.as_ref(),
            scripted_deployed.as_ref(),
        )?;
        report.insert(name.clone(), entry);
    }
    if let Some(out) = &args.out {
        write_figures(&args.inputs(), out, &args.policies, &rollouts)?;
    }
    if args.json {
        outln!("{}", Value::Object(report))?;
    } else {
        outln!("{table}")?;
    }
    Ok(())
}

/// `<out>/<phase>.png` for every phase evaluated (its training curve from
/// `<policies>/<phase>.metrics.csv` where one is bundled, beside its rollout), and
/// `<out>/training.png` (the phase policies' and the monolithic baseline's return and entropy
/// curves) when `<policies>/mission.metrics.csv` is bundled.
fn write_figures(
    inputs: &RunInputs,
    out: &Path,
    policies: &Path,
    rollouts: &[(Phase, Vec<EpisodeRow>)],
) -> Result<()> {
    let curve = |name: &str| {
        let path = policies.join(format!("{name}.metrics.csv"));
        path.is_file().then(|| plot::read_curve(&path)).transpose()
    };
    for (phase, rows) in rollouts {
        let path = out.join(format!("{}.png", phase.name()));
        let points = curve(phase.name())?.unwrap_or_default();
        inputs.check_output("--out", &path, true)?;
        atomic_file::write_with(
            &path,
            |temp| plot::phase_figure(temp, phase.name(), &points, rows),
            |e| anyhow::Error::new(e).context(format!("writing {}", path.display())),
        )?;
    }
    if let Some(mission) = curve("mission")? {
        let mut runs = Vec::new();
        for phase in [Phase::Lift, Phase::Transport, Phase::Place] {
            if let Some(points) = curve(phase.name())? {
                runs.push((phase.name(), points));
            }
        }
        runs.push(("monolithic baseline", mission));
        let path = out.join("training.png");
        inputs.check_output("--out", &path, true)?;
        atomic_file::write_with(
            &path,
            |temp| plot::comparison_figure(temp, &runs),
            |e| anyhow::Error::new(e).context(format!("writing {}", path.display())),
        )?;
    }
    Ok(())
}

/// One controller's deployed missions: their segments as the cases, and what the pipeline did.
struct DeployedCases {
    cases: Vec<(Case, Value)>,
    clamp: Value,
    /// d(U_{k−1}, Y_k) over the loaded policy ticks of every mission, by phase.
    tracking_d: deployed::TrackingD,
    /// What the clamp issued over every mission, by phase (lift, transport, place).
    clamp_by_phase: [moonhaul_coord::ClampTally; 3],
    max_grasp_force_n: f64,
    mean_grasp_force_n: f64,
    /// Missions per outcome ("completed", or the first stop and its phase).
    outcomes: std::collections::BTreeMap<String, usize>,
    /// The episode index (the stream of `--seed` its world used) of every failed mission.
    failed_episodes: Vec<usize>,
    /// The largest |onboard lift estimate − true payload height| when a gripper opened: how
    /// far the goal's ground lay from the start's (what the touchdown rule copes with), m.
    max_ground_offset_at_release_m: f64,
    /// The highest true payload height above the ground at a release: a drop, m.
    max_release_height_m: f64,
}

/// The `deployed` object of one controller.
fn deployed_json(episodes: usize, d: &DeployedCases) -> Value {
    let mut v = payload_json(episodes, &d.cases);
    if let Value::Object(map) = &mut v {
        map.insert("clamp".into(), d.clamp.clone());
        map.insert("max_grasp_force_n".into(), json!(d.max_grasp_force_n));
        map.insert("mean_grasp_force_n".into(), json!(d.mean_grasp_force_n));
        map.insert("outcomes".into(), json!(d.outcomes));
        map.insert("failed_episodes".into(), json!(d.failed_episodes));
        map.insert(
            "max_ground_offset_at_release_m".into(),
            json!(d.max_ground_offset_at_release_m),
        );
        map.insert("max_release_height_m".into(), json!(d.max_release_height_m));
    }
    v
}

/// What the clamp issued over `tally`'s ticks (the `clamp` object's own figures).
fn clamp_json(tally: &moonhaul_coord::ClampTally) -> Value {
    json!({
        "mean_t_max": tally.mean_t_max().unwrap_or(0.0),
        "clamped_tick_fraction": tally.clamped_fraction().unwrap_or(0.0),
        "hold_tick_fraction": tally.hold_fraction().unwrap_or(0.0),
        "no_step_fraction": tally.no_step_fraction().unwrap_or(0.0),
        "ticks": tally.ticks,
    })
}

/// `clamp.by_phase`: the clamp's figures over each phase's ticks (lift, transport, place), so a
/// `no_step_fraction` names the phase it comes from.
fn clamp_by_phase_json(by_phase: &[moonhaul_coord::ClampTally; 3]) -> Value {
    json!({
        "lift": clamp_json(&by_phase[0]),
        "transport": clamp_json(&by_phase[1]),
        "place": clamp_json(&by_phase[2]),
    })
}

/// `mean_tracking_d_by_phase`: the mean d(U_{k−1}, Y_k) of each phase's loaded ticks (null
/// where a phase had none).
fn tracking_d_by_phase(d: &deployed::TrackingD) -> Value {
    json!({
        "lift": d.mean_of(Phase::Lift),
        "transport": d.mean_of(Phase::Transport),
        "place": d.mean_of(Phase::Place),
    })
}

/// The deployed stack: whole missions (lift to `transport.start_height_m`, transport, place)
/// flown by each unit's onboard tick with `controller`; its phase segments as the cases, and
/// what the pipeline did. `label` prefixes the CSV folder (`scripted`, or none for learned).
fn deployed_cases(
    scene: &SceneModel,
    stack: &deployed::Stack,
    controller: &(dyn Fn() -> Result<Controller> + Sync),
    payload: PayloadKind,
    args: &EvalArgs,
    label: &str,
    progress: &mut Progress,
) -> Result<DeployedCases> {
    let name = scene.payload_name(payload);
    let controller_name = if label.is_empty() { "learned" } else { label };
    let run = progress.start(
        format!("{name} {controller_name} deployed"),
        args.episodes,
        "missions",
        args.episodes as u64,
        "missions",
    );
    let missions = deployed::missions(
        scene,
        stack,
        controller,
        args.episodes_of(payload),
        false,
        run.bar(),
    )
    .with_context(|| format!("deployed {label} {name}"))?;
    run.finish();
    let mut cases = Vec::new();
    for case in [Case::ALL[0], Case::ALL[3], Case::ALL[4]] {
        let episodes: Vec<Vec<EpisodeRow>> = missions
            .iter()
            .map(|m| match case.phase {
                Phase::Lift => m.segments.lift.clone(),
                Phase::Transport => m.segments.transport.clone(),
                _ => m.segments.place.clone(),
            })
            .collect();
        if let Some(out) = &args.out {
            write_episodes(
                &args.inputs(),
                &out.join(label)
                    .join(&name)
                    .join("deployed")
                    .join(case.name()),
                &episodes,
            )?;
        }
        // A mission that never reached a phase has no rows to judge it by: it failed it.
        let reached: Vec<Vec<EpisodeRow>> = episodes
            .into_iter()
            .filter(|rows| !rows.is_empty())
            .collect();
        let mut summary = if reached.is_empty() {
            json!({})
        } else {
            summarize(case, &reached)?
        };
        if let Value::Object(map) = &mut summary {
            map.insert(
                "reached_rate".into(),
                json!(reached.len() as f64 / missions.len().max(1) as f64),
            );
        }
        cases.push((case, summary));
    }
    let sum = |f: fn(&deployed::DeployedMission) -> f64| missions.iter().map(f).sum::<f64>();
    let mut by_phase = [moonhaul_coord::ClampTally::default(); 3];
    let mut tracking_d = deployed::TrackingD::default();
    for m in &missions {
        for (sum, t) in by_phase.iter_mut().zip(&m.clamp_by_phase) {
            sum.merge(t);
        }
        tracking_d.merge(&m.tracking_d);
    }
    let mut tally = moonhaul_coord::ClampTally::default();
    by_phase.iter().for_each(|t| tally.merge(t));
    let n = missions.len().max(1) as f64;
    let mut clamp = clamp_json(&tally);
    if let Value::Object(map) = &mut clamp {
        map.insert(
            "mean_tracking_d".into(),
            json!(tracking_d.mean().unwrap_or(0.0)),
        );
        map.insert(
            "mean_tracking_d_by_phase".into(),
            tracking_d_by_phase(&tracking_d),
        );
        map.insert("by_phase".into(), clamp_by_phase_json(&by_phase));
        map.insert(
            "completed_rate".into(),
            json!(missions.iter().filter(|m| m.completed).count() as f64 / n),
        );
    }
    Ok(DeployedCases {
        cases,
        clamp,
        tracking_d,
        clamp_by_phase: by_phase,
        max_grasp_force_n: missions
            .iter()
            .map(|m| m.max_grasp_force_n)
            .fold(0.0, f64::max),
        mean_grasp_force_n: sum(|m| m.mean_grasp_force_n) / n,
        max_ground_offset_at_release_m: missions
            .iter()
            .filter_map(|m| m.ground_offset_at_release_m)
            .fold(0.0, |max, o| o.abs().max(max)),
        max_release_height_m: missions
            .iter()
            .filter_map(|m| m.release_height_m)
            .fold(0.0, f64::max),
        failed_episodes: (0..missions.len())
            .filter(|&k| !missions[k].completed)
            .collect(),
        outcomes: missions.iter().fold(Default::default(), |mut counts, m| {
            *counts.entry(m.outcome.clone()).or_default() += 1;
            counts
        }),
    })
}

/// The scripted missions the cases `wanted` need, as (lift case, its height): one per lift
/// case asked for, and the 0.3 m one for transport and place.
fn scripted_missions(wanted: &[Case]) -> Vec<(Case, f64)> {
    Case::ALL
        .into_iter()
        .filter_map(|case| {
            let h = case.goal_height_m?;
            let needed = wanted.contains(&case)
                || ((h - 0.3).abs() < 1e-9 && wanted.iter().any(|c| c.goal_height_m.is_none()));
            needed.then_some((case, h))
        })
        .collect()
}

/// The scripted baseline: one mission per lift height, its segments as the cases.
fn scripted_cases(
    scene: &SceneModel,
    plan: &MissionPlan,
    payload: PayloadKind,
    wanted: &[Case],
    args: &EvalArgs,
    progress: &mut Progress,
) -> Result<Vec<(Case, Value)>> {
    let mut cases = Vec::new();
    let name = scene.payload_name(payload);
    for (case, h) in scripted_missions(wanted) {
        let run = progress.start(
            format!("{name} scripted lift {h} m"),
            args.episodes,
            "missions",
            args.episodes as u64,
            "missions",
        );
        let missions = rollout::scripted(scene, plan, h, args.episodes_of(payload), run.bar())
            .with_context(|| format!("scripted {name} lift {h} m"))?;
        run.finish();
        let pick = |f: fn(&ScriptedSegments) -> &Vec<EpisodeRow>| {
            missions.iter().map(|m| f(m).clone()).collect::<Vec<_>>()
        };
        let mut segments = vec![(case, pick(|m| &m.lift))];
        // Transport and place come from the mission at the paper's 0.3 m transport height.
        if (h - 0.3).abs() < 1e-9 {
            for phase_case in &Case::ALL[3..] {
                let rows = match phase_case.phase {
                    Phase::Transport => pick(|m| &m.transport),
                    _ => pick(|m| &m.place),
                };
                segments.push((*phase_case, rows));
            }
        }
        segments.retain(|(case, _)| wanted.contains(case));
        for (case, episodes) in segments {
            if let Some(out) = &args.out {
                write_episodes(
                    &args.inputs(),
                    &out.join("scripted")
                        .join(scene.payload_name(payload))
                        .join(case.name()),
                    &episodes,
                )?;
            }
            cases.push((case, summarize(case, &episodes)?));
        }
    }
    Ok(cases)
}

fn cell(summary: Option<&Value>, metric: &str) -> String {
    let m = summary.and_then(|s| s.get(metric));
    match (
        m.and_then(|m| m["mean"].as_f64()),
        m.and_then(|m| m["sd"].as_f64()),
    ) {
        (Some(mean), Some(sd)) => format!("{mean:.3} ± {sd:.3}"),
        _ => "-".into(),
    }
}

/// The summary of `case` in a set of case summaries.
fn find_case<'a>(set: Option<&'a [(Case, Value)]>, case: &Case) -> Option<&'a Value> {
    set.and_then(|s| s.iter().find(|(c, _)| c == case).map(|(_, v)| v))
}

/// One payload's table: the cases' metrics per controller (the gate+clamp column is the
/// learned policies' deployed missions), then how each controller's deployed missions ended
/// and how far its drives trailed their commands in each phase.
#[allow(clippy::too_many_arguments)]
fn write_table(
    out: &mut String,
    payload: &str,
    episodes: usize,
    randomize: bool,
    learned: &[(Case, Value)],
    scripted: Option<&[(Case, Value)]>,
    learned_deployed: Option<&DeployedCases>,
    scripted_deployed: Option<&DeployedCases>,
) -> Result<()> {
    let fmt = |e: std::fmt::Error| anyhow::anyhow!("formatting the table: {e}");
    let deployed = learned_deployed.map(|d| d.cases.as_slice());
    writeln!(
        out,
        "\n{payload} — {episodes} episodes per case, {}",
        if randomize {
            "domain randomization on"
        } else {
            "nominal world (flat, no noise)"
        }
    )
    .map_err(fmt)?;
    writeln!(
        out,
        "{:<10} {:<24} {:>8}  {:>22}  {:>22}  {:>22}",
        "case",
        "metric",
        "paper",
        "learned (mean ± sd)",
        "scripted IK (mean ± sd)",
        "gate+clamp (mean ± sd)"
    )
    .map_err(fmt)?;
    for (case, summary) in learned {
        let name = case.name();
        let (scripted, deployed) = (find_case(scripted, case), find_case(deployed, case));
        let Value::Object(metrics) = summary else {
            continue;
        };
        for metric in metrics.keys() {
            let paper = paper_value(&name, metric).map_or("-".into(), |v| {
                if metric == "steady_tilt_deg" && case.phase == Phase::Lift {
                    format!("<{v}")
                } else {
                    format!("{v}")
                }
            });
            writeln!(
                out,
                "{:<10} {:<24} {:>8}  {:>22}  {:>22}  {:>22}",
                name,
                metric,
                paper,
                cell(Some(summary), metric),
                cell(scripted, metric),
                cell(deployed, metric)
            )
            .map_err(fmt)?;
        }
    }
    for (controller, d) in [
        ("learned", learned_deployed),
        ("scripted IK", scripted_deployed),
    ] {
        if let Some(d) = d {
            write_deployed_outcomes(out, controller, d).map_err(fmt)?;
        }
    }
    Ok(())
}

/// The deployed missions of one controller below the table: completed of total, the mean
/// d(U_{k−1}, Y_k) of each phase's loaded ticks, each phase's holds and ticks without an
/// admissible step, then every outcome with its count.
fn write_deployed_outcomes(
    out: &mut String,
    controller: &str,
    d: &DeployedCases,
) -> std::fmt::Result {
    let missions: usize = d.outcomes.values().sum();
    let completed = d.outcomes.get("completed").copied().unwrap_or(0);
    let mean = |v: Option<f64>| v.map_or("-".to_owned(), |v| format!("{v:.3}"));
    writeln!(
        out,
        "gate+clamp, {controller}: {completed}/{missions} missions completed; mean \
         d(U_{{k−1}}, Y_k) loaded: lift {}, transport {}, place {} (all {})",
        mean(d.tracking_d.mean_of(Phase::Lift)),
        mean(d.tracking_d.mean_of(Phase::Transport)),
        mean(d.tracking_d.mean_of(Phase::Place)),
        mean(d.tracking_d.mean()),
    )?;
    let percent = |v: Option<f64>| v.map_or("-".to_owned(), |v| format!("{:.2} %", 100.0 * v));
    let [lift, transport, place] = &d.clamp_by_phase;
    writeln!(
        out,
        "  holds / no admissible step: lift {} / {}, transport {} / {}, place {} / {}",
        percent(lift.hold_fraction()),
        percent(lift.no_step_fraction()),
        percent(transport.hold_fraction()),
        percent(transport.no_step_fraction()),
        percent(place.hold_fraction()),
        percent(place.no_step_fraction()),
    )?;
    for (outcome, count) in d.outcomes.iter().filter(|(o, _)| *o != "completed") {
        writeln!(out, "  {count:>5} × {outcome}")?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_says_how_deployed_missions_ended_and_each_phases_tracking() {
        let mut tracking_d = deployed::TrackingD::default();
        tracking_d.add(Phase::Lift, 0.1);
        tracking_d.add(Phase::Transport, 0.3);
        let mut clamp_by_phase = [moonhaul_coord::ClampTally::default(); 3];
        for _ in 0..3 {
            clamp_by_phase[0].record(1.0, None);
        }
        clamp_by_phase[0].record(0.0, Some(moonhaul_coord::HoldReason::NoAdmissibleStep));
        clamp_by_phase[2].record(0.5, None);
        let d = DeployedCases {
            cases: Vec::new(),
            clamp: json!({}),
            tracking_d,
            clamp_by_phase,
            max_grasp_force_n: 0.0,
            mean_grasp_force_n: 0.0,
            outcomes: [
                ("completed".to_owned(), 8),
                ("unit 1 stopped in transport: tracking fault".to_owned(), 2),
            ]
            .into(),
            failed_episodes: vec![3, 7],
            max_ground_offset_at_release_m: 0.0,
            max_release_height_m: 0.0,
        };
        let mut out = String::new();
        write_deployed_outcomes(&mut out, "scripted IK", &d).unwrap();
        let lines: Vec<&str> = out.lines().collect();
        assert_eq!(
            lines,
            [
                "gate+clamp, scripted IK: 8/10 missions completed; mean d(U_{k−1}, Y_k) \
                 loaded: lift 0.100, transport 0.300, place - (all 0.200)",
                "  holds / no admissible step: lift 25.00 % / 25.00 %, transport - / -, \
                 place 0.00 % / 0.00 %",
                "      2 × unit 1 stopped in transport: tracking fault",
            ]
        );
        assert_eq!(
            tracking_d_by_phase(&tracking_d),
            json!({"lift": 0.1, "transport": 0.3, "place": null})
        );
        let by_phase = clamp_by_phase_json(&d.clamp_by_phase);
        assert_eq!(by_phase["lift"]["no_step_fraction"], json!(0.25));
        assert_eq!(by_phase["lift"]["ticks"], json!(4));
        assert_eq!(by_phase["place"]["mean_t_max"], json!(0.5));
        assert_eq!(by_phase["transport"]["ticks"], json!(0));
    }
}
