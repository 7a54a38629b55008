//! `moonhaul eval`: the paper's simulation results table, measured — the bundled phase
//! policies (learned) beside the scripted IK controller (a model-based baseline the paper
//! lacks), over seeded, randomized episodes of every case and payload. Metrics are defined in
//! [`crate::eval::metrics`]; `--out` writes every episode's rows so they can be recomputed.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use moonhaul_core::state::Phase;
use moonhaul_sim::scripted::MissionPlan;
use moonhaul_sim::task::{PhaseTask, TaskConfig};
use moonhaul_sim::{PayloadKind, SceneModel, SimConfig};
use serde_json::{json, Map, Value};

use crate::eval::episode::{read_csv, write_csv, EpisodeRow};
use crate::eval::metrics::{self, lift_summary, place_summary, transport_summary};
use crate::eval::rollout::{self, Case, Episodes, ScriptedSegments};

#[derive(clap::Args)]
pub struct EvalArgs {
    /// Folder holding lift.safetensors, transport.safetensors and place.safetensors.
    #[arg(long, default_value = "assets/policies")]
    policies: PathBuf,
    /// Payloads to evaluate (box, bricks, sledge), comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "box,bricks,sledge")]
    payload: Vec<PayloadKind>,
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
    /// Write every episode's rows to DIR/<payload>/<case>/<episode>.csv (scripted ones under
    /// DIR/scripted/).
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
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

/// The summary of one case's episodes.
fn summarize(case: Case, episodes: &[Vec<EpisodeRow>]) -> Result<Value> {
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

fn write_episodes(dir: &Path, episodes: &[Vec<EpisodeRow>]) -> Result<()> {
    for (k, rows) in episodes.iter().enumerate() {
        write_csv(&dir.join(format!("{k:03}.csv")), rows)?;
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
fn recompute(dir: &Path, payloads: &[PayloadKind]) -> Result<()> {
    let mut report = Map::new();
    for &payload in payloads {
        let mut cases = Vec::new();
        let mut episodes = 0;
        for case in Case::ALL {
            let rows = read_episodes(&dir.join(payload.name()).join(case.name()))?;
            episodes = rows.len();
            cases.push((case, summarize(case, &rows)?));
        }
        report.insert(payload.name().into(), payload_json(episodes, &cases));
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
    let sim = SimConfig::load(&args.sim)?;
    let tasks = TaskConfig::load(&args.tasks)?;
    let plan = MissionPlan::load(&args.mission)?;
    let scene = SceneModel::new(sim).context("building the scene")?;
    let randomize = !args.no_randomization;
    let mut policies = Vec::new();
    for phase in [Phase::Lift, Phase::Transport, Phase::Place] {
        let path = args.policies.join(format!("{}.safetensors", phase.name()));
        let task = PhaseTask::new(phase, tasks, &scene)?;
        policies.push((phase, task, rollout::load_policy(&path, phase)?));
    }

    let mut report = Map::new();
    let mut table = String::new();
    for &payload in &args.payload {
        let mut learned = Vec::new();
        for case in Case::ALL {
            let (_, task, policy) = policies
                .iter()
                .find(|(p, ..)| *p == case.phase)
                .context("every phase has a policy")?;
            let episodes = rollout::learned(&scene, task, policy, case, args.episodes_of(payload))
                .with_context(|| format!("{} {}", payload.name(), case.name()))?;
            if let Some(out) = &args.out {
                write_episodes(&out.join(payload.name()).join(case.name()), &episodes)?;
            }
            learned.push((case, summarize(case, &episodes)?));
        }
        let scripted = if args.no_scripted {
            None
        } else {
            Some(scripted_cases(&scene, &plan, payload, &args)?)
        };
        let mut entry = payload_json(args.episodes, &learned);
        if let (Some(scripted), Value::Object(map)) = (&scripted, &mut entry) {
            map.insert("scripted".into(), payload_json(args.episodes, scripted));
        }
        write_table(
            &mut table,
            payload,
            args.episodes,
            randomize,
            &learned,
            scripted.as_deref(),
        )?;
        report.insert(payload.name().into(), entry);
    }
    if args.json {
        outln!("{}", Value::Object(report))?;
    } else {
        outln!("{table}")?;
    }
    Ok(())
}

/// The scripted baseline: one mission per lift height, its segments as the cases.
fn scripted_cases(
    scene: &SceneModel,
    plan: &MissionPlan,
    payload: PayloadKind,
    args: &EvalArgs,
) -> Result<Vec<(Case, Value)>> {
    let mut cases = Vec::new();
    for case in Case::ALL {
        let Some(h) = case.goal_height_m else {
            continue;
        };
        let missions = rollout::scripted(scene, plan, h, args.episodes_of(payload))
            .with_context(|| format!("scripted {} lift {h} m", payload.name()))?;
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
        for (case, episodes) in segments {
            if let Some(out) = &args.out {
                write_episodes(
                    &out.join("scripted").join(payload.name()).join(case.name()),
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

fn write_table(
    out: &mut String,
    payload: PayloadKind,
    episodes: usize,
    randomize: bool,
    learned: &[(Case, Value)],
    scripted: Option<&[(Case, Value)]>,
) -> Result<()> {
    let fmt = |e: std::fmt::Error| anyhow::anyhow!("formatting the table: {e}");
    writeln!(
        out,
        "\n{} — {episodes} episodes per case, {}",
        payload.name(),
        if randomize {
            "domain randomization on"
        } else {
            "nominal world (flat, no noise)"
        }
    )
    .map_err(fmt)?;
    writeln!(
        out,
        "{:<10} {:<24} {:>8}  {:>22}  {:>22}",
        "case", "metric", "paper", "learned (mean ± sd)", "scripted IK (mean ± sd)"
    )
    .map_err(fmt)?;
    for (case, summary) in learned {
        let name = case.name();
        let scripted = scripted.and_then(|s| s.iter().find(|(c, _)| c == case).map(|(_, v)| v));
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
                "{:<10} {:<24} {:>8}  {:>22}  {:>22}",
                name,
                metric,
                paper,
                cell(Some(summary), metric),
                cell(scripted, metric)
            )
            .map_err(fmt)?;
        }
    }
    Ok(())
}
