//! `moonhaul sim`: run the scripted mission in the simulator (CSV + PNG), and measure the
//! simulator's speed and accuracy.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use moonhaul_core::input::read_capped_text;
use moonhaul_core::overwrite::RunInputs;
use moonhaul_core::state::{Phase, UnitCommand, UNIT_ACTION_DIM};
use moonhaul_sim::accuracy;
use moonhaul_sim::scene::UNITS;
use moonhaul_sim::scripted::{run_mission, MissionPlan, ScriptedController};
use moonhaul_sim::{BatchEnv, Env, EnvOptions, SceneModel, SimConfig};
use plotters::prelude::*;

use crate::payload_arg::{self, PayloadArg};

#[derive(clap::Subcommand)]
pub enum SimCommand {
    /// Run the scripted mission (lift 0.3 m, drive 2 m at 0.2 m/s, set down, release) and
    /// write DIR/demo.csv (one row per control step) and DIR/demo.png (payload height, top,
    /// and tilt, bottom, over time; grid every 5 s, 0.1 m and 1 degree).
    Demo {
        /// Payload: box, bricks, sledge, gen<i> (generated), or a payload URDF (a path ending
        /// in .urdf or containing /; one link `payload` with one <box> collision, long side
        /// along x).
        #[arg(long)]
        payload: PayloadArg,
        /// Seed of the env's random stream.
        #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
        seed: u64,
        /// Nominal world: flat ground, mid-range friction, no command noise or joint offsets.
        #[arg(long)]
        no_randomization: bool,
        /// Output folder (created if missing) for demo.csv and demo.png.
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
        /// Replace an existing demo.csv and demo.png (never an input of the run).
        #[arg(long)]
        force: bool,
        /// Simulator config.
        #[arg(long, default_value = "configs/sim.toml")]
        config: PathBuf,
        /// Scripted mission plan.
        #[arg(long, default_value = "configs/mission.toml")]
        mission: PathBuf,
    },
    /// Measure control and physics (integration) steps per second for one env and for a batch
    /// replaying the scripted mission's commands under domain randomization, and the accuracy
    /// of the configured solver settings against a fine reference.
    Bench {
        /// Print only the batched result as one JSON line.
        #[arg(long)]
        json: bool,
        /// Envs in the batch, 1 to 4096.
        #[arg(long, allow_negative_numbers = true, default_value_t = 64)]
        envs: usize,
        /// Worker threads (0: one per core; at most 1024).
        #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
        threads: usize,
        /// Control steps per env (default: 10 s of the scripted mission), 1 to 1000000; envs
        /// × steps at most 10000000.
        #[arg(long, allow_negative_numbers = true, default_value_t = 500)]
        steps: usize,
        /// Simulator config.
        #[arg(long, default_value = "configs/sim.toml")]
        config: PathBuf,
        /// Scripted mission plan.
        #[arg(long, default_value = "configs/mission.toml")]
        mission: PathBuf,
        /// Replay these commands instead of the scripted mission's: a JSON object whose
        /// `commands` holds one `[[wheel_l, wheel_r, q1..q7], [..]]` pair per control step (the
        /// format of bench/mujoco/plan.json, which the MuJoCo benchmark replays).
        #[arg(long, value_name = "FILE")]
        plan: Option<PathBuf>,
    },
    /// Fly seeded missions through the deployed stack (onboard tick, gate, clamp) and write
    /// where each completed one handed over to transport and to place: the starts the
    /// transport and place trainings mix in (`[world] handovers` of their configs).
    Handovers(crate::handover_cmd::HandoverArgs),
}

pub fn run(cmd: SimCommand) -> Result<()> {
    match cmd {
        SimCommand::Handovers(args) => crate::handover_cmd::run(args),
        SimCommand::Demo {
            payload,
            seed,
            no_randomization,
            out,
            force,
            config,
            mission,
        } => demo(
            &payload,
            seed,
            !no_randomization,
            &out,
            force,
            &config,
            &mission,
        ),
        SimCommand::Bench {
            json,
            envs,
            threads,
            steps,
            config,
            mission,
            plan,
        } => bench(
            json,
            envs,
            threads,
            steps,
            &config,
            &mission,
            plan.as_deref(),
        ),
    }
}

fn load_scene(config: &Path) -> Result<SceneModel> {
    let config = SimConfig::load(config).context("cannot load the simulator config")?;
    SceneModel::new(config).context("cannot build the simulated scene")
}

/// One CSV row per control step.
struct Row {
    t_s: f64,
    phase: Phase,
    height_m: f64,
    tilt_deg: f64,
    speed_mps: f64,
    force_n: [f64; UNITS],
    torque_nm: [f64; UNITS],
    x_m: f64,
    contact: bool,
}

/// Creates the output folder before the mission runs, so a path that cannot be one (an
/// existing file, a folder under a file, no permission) fails at once, by name.
fn prepare_out_dir(out: &Path) -> Result<()> {
    if out.exists() && !out.is_dir() {
        bail!("--out {}: exists and is not a folder", out.display());
    }
    std::fs::create_dir_all(out)
        .with_context(|| format!("--out {}: cannot create the output folder", out.display()))?;
    if !out.is_dir() {
        bail!("--out {}: is not a folder", out.display());
    }
    Ok(())
}

fn load_mission(mission: &Path) -> Result<MissionPlan> {
    MissionPlan::load(mission).context("cannot load the mission plan")
}

fn demo(
    payload: &PayloadArg,
    seed: u64,
    randomize: bool,
    out: &Path,
    force: bool,
    config: &Path,
    mission: &Path,
) -> Result<()> {
    let mut inputs = RunInputs::new();
    inputs
        .add("simulator config", config)
        .add("mission plan", mission);
    if let PayloadArg::File(path) = payload {
        inputs.add("payload", path);
    }
    for file in ["demo.csv", "demo.png"] {
        inputs.check_output("--out", &out.join(file), force)?;
    }
    prepare_out_dir(out)?;
    let mut scene = load_scene(config)?;
    let payload = payload_arg::resolve(&mut scene, payload)?;
    let plan = load_mission(mission)?;
    let options = EnvOptions {
        randomize,
        payload: Some(payload),
        start_lift_m: 0.0,
    };
    let mut env = Env::new(&scene, seed, options).context("cannot create the env")?;
    let mut rows = Vec::new();
    let summary = run_mission(&scene, &mut env, plan, |phase, s| {
        rows.push(Row {
            t_s: s.time_s,
            phase,
            height_m: s.payload.height_m,
            tilt_deg: s.payload.tilt_rad.to_degrees(),
            speed_mps: s.payload.linvel_mps.norm(),
            force_n: s.units.map(|u| u.grasp.force_n),
            torque_nm: s.units.map(|u| u.grasp.torque_nm),
            x_m: s.payload.pose.translation.x,
            contact: s.payload.ground_contact,
        })
    })
    .context("scripted mission failed")?;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let mut csv = String::from(
        "t_s,phase,payload_height_m,payload_tilt_deg,payload_speed_mps,grasp_force_1_n,\
         grasp_force_2_n,grasp_torque_1_nm,grasp_torque_2_nm,payload_x_m,payload_ground_contact\n",
    );
    for r in &rows {
        let _ = writeln!(
            csv,
            "{:.3},{},{:.5},{:.4},{:.5},{:.3},{:.3},{:.3},{:.3},{:.5},{}",
            r.t_s,
            r.phase,
            r.height_m,
            r.tilt_deg,
            r.speed_mps,
            r.force_n[0],
            r.force_n[1],
            r.torque_nm[0],
            r.torque_nm[1],
            r.x_m,
            u8::from(r.contact)
        );
    }
    write_outputs(&out.join("demo.csv"), &csv, &out.join("demo.png"), &rows)?;
    outln!(
        "{} ({}): max height {:.3} m, max tilt {:.2} deg, travel {:.3} m, touchdown {:.3} m/s, \
         max grasp force {:.1} N, grasp drift {:.2} mm / {:.3} deg, broken: {}",
        scene.payload_name(payload),
        if randomize {
            format!("randomized, seed {seed}")
        } else {
            "nominal".into()
        },
        summary.max_height_m,
        summary.max_tilt_rad.to_degrees(),
        summary.travel_m,
        summary.touchdown_speed_mps,
        summary.max_grasp_force_n,
        summary.max_grasp_drift_m * 1e3,
        summary.max_grasp_drift_rad.to_degrees(),
        summary.grasp_broken
    )?;
    outln!(
        "wrote {} and {}",
        out.join("demo.csv").display(),
        out.join("demo.png").display()
    )?;
    Ok(())
}

/// Writes the CSV and its plot as one group ([`moonhaul_core::atomic_file::Group`]): each
/// whole or not at all, and a reader never sees a new CSV beside an old plot or the reverse.
fn write_outputs(csv_path: &Path, csv: &str, png_path: &Path, rows: &[Row]) -> Result<()> {
    let cannot_write = |path: &Path| format!("cannot write {}", path.display());
    let mut outputs = moonhaul_core::atomic_file::Group::new(|path: &Path, e: std::io::Error| {
        anyhow::Error::new(e).context(cannot_write(path))
    });
    outputs.stage(csv_path, |temp| {
        std::fs::write(temp, csv).with_context(|| cannot_write(csv_path))
    })?;
    outputs.stage(png_path, |temp| {
        plot(temp, rows).with_context(|| cannot_write(png_path))
    })?;
    outputs.publish()
}

/// Two panels over mission time: payload height (m) on top, tilt (deg) below.
fn plot(path: &Path, rows: &[Row]) -> Result<()> {
    moonhaul_core::plot_font::register().map_err(anyhow::Error::msg)?;
    let root = BitMapBackend::new(path, (1200, 800)).into_drawing_area();
    root.fill(&WHITE)?;
    let panels = root.split_evenly((2, 1));
    let t_end = rows.last().map_or(1.0, |r| r.t_s).max(1.0);
    // (title, axis label, values, smallest span, colour) per panel.
    let series = [
        (
            "Payload height",
            "height above ground (m)",
            rows.iter().map(|r| r.height_m).collect::<Vec<_>>(),
            0.1,
            BLUE,
        ),
        (
            "Payload tilt",
            "tilt (deg)",
            rows.iter().map(|r| r.tilt_deg).collect(),
            1.0,
            RED,
        ),
    ];
    for (panel, (title, y_desc, values, span, color)) in panels.iter().zip(series) {
        let (lo, hi) = values
            .iter()
            .fold((0.0f64, span), |(lo, hi): (f64, f64), v| {
                (lo.min(*v), hi.max(*v))
            });
        let pad = 0.05 * (hi - lo);
        let mut chart = ChartBuilder::on(panel)
            .caption(title, (moonhaul_core::plot_font::FAMILY, 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..t_end, (lo - pad)..(hi + pad))?;
        chart
            .configure_mesh()
            .x_desc("mission time (s)")
            .y_desc(y_desc)
            .label_style((moonhaul_core::plot_font::FAMILY, 15))
            .axis_desc_style((moonhaul_core::plot_font::FAMILY, 16))
            .light_line_style(RGBColor(235, 235, 235))
            .draw()?;
        chart.draw_series(LineSeries::new(
            rows.iter().zip(&values).map(|(r, v)| (r.t_s, *v)),
            color.stroke_width(2),
        ))?;
    }
    root.present()?;
    Ok(())
}

/// The scripted mission's commands for `steps` control steps of a nominal run; every env of a
/// batch replays them, so the bench times the simulator, not the controller.
fn scripted_commands(
    scene: &SceneModel,
    plan: MissionPlan,
    steps: usize,
) -> Result<Vec<[UnitCommand; UNITS]>> {
    let mut env = Env::new(
        scene,
        0,
        EnvOptions {
            randomize: false,
            payload: None,
            start_lift_m: 0.0,
        },
    )?;
    let mut state = env.state(scene);
    let mut controller = ScriptedController::new(plan, scene, &state)?;
    let mut commands = Vec::with_capacity(steps);
    for _ in 0..steps {
        let (_, command) = controller.command(scene, state.time_s, &state)?;
        env.step(scene, &command);
        env.state_into(scene, &mut state);
        commands.push(command);
    }
    Ok(commands)
}

/// Largest plan file read, bytes: 10⁶ steps of two 9-number commands are ~400 MB of JSON.
const MAX_PLAN_BYTES: u64 = 512 << 20;

/// The first `steps` commands of a plan file (see `Bench::plan`); every error names the file
/// and, for a bad command, its step and unit.
fn plan_commands(path: &Path, steps: usize) -> Result<Vec<[UnitCommand; UNITS]>> {
    /// One `[wheel_l, wheel_r, q1..q7]` per unit: the action layout of `UnitCommand`.
    #[derive(serde::Deserialize)]
    struct Plan {
        commands: Vec<[[f64; UNIT_ACTION_DIM]; UNITS]>,
    }
    let name = path.display();
    let text = read_capped_text(path, MAX_PLAN_BYTES)
        .with_context(|| format!("cannot read plan {name}"))?;
    let plan: Plan = serde_json::from_str(&text)
        .with_context(|| format!("plan {name} is not a command plan"))?;
    if plan.commands.len() < steps {
        bail!(
            "plan {name} has {} commands, fewer than --steps {steps}",
            plan.commands.len()
        );
    }
    plan.commands[..steps]
        .iter()
        .enumerate()
        .map(|(step, pair)| {
            for (unit, values) in pair.iter().enumerate() {
                if let Some(bad) = values.iter().position(|v| !v.is_finite()) {
                    bail!("plan {name}: commands[{step}][{unit}][{bad}] is not finite");
                }
            }
            Ok(pair.map(|action| UnitCommand::from_action(&action)))
        })
        .collect()
}

/// Median costs of one env on the calling thread, s.
struct ResetCost {
    /// [`Env::reset`]: restoring the built world.
    reset_s: f64,
    /// Building a new world ([`Env::new`]), what a reset cost before templates.
    rebuild_s: f64,
    /// One control step of the replayed plan.
    step_s: f64,
}

/// Times resets, rebuilds and control steps of one randomized env alternately (one episode of
/// up to 25 steps of the plan between resets), so all three see the same machine load.
fn reset_cost(scene: &SceneModel, plan: &[[UnitCommand; UNITS]]) -> Result<ResetCost> {
    const ROUNDS: usize = 20;
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let episode = &plan[..plan.len().min(25)];
    let mut env = Env::new(scene, 1, EnvOptions::default())?;
    let (mut resets, mut rebuilds, mut steps) = (vec![], vec![], vec![]);
    for round in 0..ROUNDS {
        let start = Instant::now();
        for command in episode {
            env.step(scene, command);
        }
        steps.push(start.elapsed().as_secs_f64() / episode.len() as f64);
        let start = Instant::now();
        env.reset();
        resets.push(start.elapsed().as_secs_f64());
        let start = Instant::now();
        let rebuilt = Env::new(scene, round as u64 + 2, EnvOptions::default())?;
        rebuilds.push(start.elapsed().as_secs_f64());
        drop(rebuilt);
    }
    Ok(ResetCost {
        reset_s: median(resets),
        rebuild_s: median(rebuilds),
        step_s: median(steps),
    })
}

/// Most envs in a bench batch: an env holds ~0.9 MB, so the largest batch takes ~4 GB.
const MAX_BENCH_ENVS: usize = 4096;
/// Most control steps per env: 10⁶ steps are 5.5 h of simulated time at 50 Hz (the commands
/// replayed take 144 MB); one env runs them in ~5 min on one core.
const MAX_BENCH_STEPS: usize = 1_000_000;
/// Most env steps (envs × steps) of one bench: ~20 min at the ~8000 env steps/s of a
/// two-core machine, never hours or days.
const MAX_BENCH_ENV_STEPS: usize = 10_000_000;
/// Most worker threads (far above any core count; each thread reserves a stack).
const MAX_BENCH_THREADS: usize = 1024;

/// Every bad combination of bench arguments is an error naming the argument.
fn check_bench_args(envs: usize, threads: usize, steps: usize) -> Result<()> {
    if !(1..=MAX_BENCH_ENVS).contains(&envs) {
        bail!("--envs must be in 1..={MAX_BENCH_ENVS}, got {envs}");
    }
    if !(1..=MAX_BENCH_STEPS).contains(&steps) {
        bail!("--steps must be in 1..={MAX_BENCH_STEPS}, got {steps}");
    }
    if threads > MAX_BENCH_THREADS {
        bail!("--threads must be 0 (one per core) or at most {MAX_BENCH_THREADS}, got {threads}");
    }
    if envs
        .checked_mul(steps)
        .is_none_or(|total| total > MAX_BENCH_ENV_STEPS)
    {
        bail!(
            "--envs {envs} × --steps {steps} is more than the {MAX_BENCH_ENV_STEPS} env steps \
             one bench may run"
        );
    }
    Ok(())
}

fn bench(
    json: bool,
    envs: usize,
    threads: usize,
    steps: usize,
    config: &Path,
    mission: &Path,
    plan_file: Option<&Path>,
) -> Result<()> {
    check_bench_args(envs, threads, steps)?;
    let scene = load_scene(config)?;
    let mission = load_mission(mission)?;
    let decimation = scene.decimation() as f64;
    let plan = match plan_file {
        Some(path) => plan_commands(path, steps)?,
        None => scripted_commands(&scene, mission, steps)?,
    };
    let first = *plan
        .first()
        .context("the scripted mission gave no commands")?;
    // The JSON line reports the batch only; the table compares it with one env on one thread.
    let runs: &[(usize, usize)] = if json {
        &[(envs, threads)]
    } else {
        &[(1, 1), (envs, threads)]
    };
    let mut rates = Vec::new();
    for &(count, threads) in runs {
        let mut batch = BatchEnv::new(scene.clone(), count, 1, EnvOptions::default(), threads)?;
        let mut commands = vec![first; count];
        let start = Instant::now();
        for step in &plan {
            commands.iter_mut().for_each(|c| *c = *step);
            batch.step(&commands)?;
        }
        let elapsed = start.elapsed().as_secs_f64();
        if elapsed <= 0.0 {
            bail!(
                "the clock did not advance over {} control steps",
                plan.len()
            );
        }
        let control = count as f64 * plan.len() as f64 / elapsed;
        rates.push((count, batch.threads(), control, control * decimation));
    }
    let &(n, t, control, physics) = rates.last().context("no bench ran")?;
    let resets = reset_cost(&scene, &plan)?;
    if json {
        outln!(
            "{}",
            serde_json::json!({
                "envs": n,
                "threads": t,
                "control_steps_per_s": control,
                "physics_steps_per_s": physics,
                "reset_s": resets.reset_s,
                "rebuild_s": resets.rebuild_s,
                "control_step_s": resets.step_s,
            })
        )?;
        return Ok(());
    }
    let p = &scene.config.physics;
    outln!(
        "config: {} Hz integration, {} Hz collision detection, {} Hz control, {} PGS sweep(s)",
        p.physics_hz,
        p.collision_hz,
        scene.config.control_hz,
        p.num_internal_pgs_iterations
    )?;
    for (n, t, control, physics) in &rates {
        outln!(
            "{n:>5} env(s) on {t} thread(s): {control:>9.0} control steps/s, {physics:>9.0} physics steps/s"
        )?;
    }
    outln!(
        "reset of one env (one thread): {:.3} ms = {:.2} control steps ({:.3} ms each); \
         rebuilding it instead: {:.2} ms = {:.1} control steps",
        resets.reset_s * 1e3,
        resets.reset_s / resets.step_s,
        resets.step_s * 1e3,
        resets.rebuild_s * 1e3,
        resets.rebuild_s / resets.step_s,
    )?;
    let report = accuracy::compare(&scene, mission).context("accuracy run failed")?;
    outln!("{report}")?;
    Ok(())
}
