//! `moonhaul sim`: run the scripted mission in the simulator (CSV + PNG), and measure the
//! simulator's speed and accuracy.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use moonhaul_core::state::{Phase, UnitCommand};
use moonhaul_sim::accuracy;
use moonhaul_sim::scene::UNITS;
use moonhaul_sim::scripted::{run_mission, ScriptedController};
use moonhaul_sim::{BatchEnv, Env, EnvOptions, PayloadKind, SceneModel, SimConfig};
use plotters::prelude::*;

#[derive(clap::Subcommand)]
pub enum SimCommand {
    /// Run the scripted mission (lift 0.3 m, drive 2 m at 0.2 m/s, set down, release) and
    /// write DIR/demo.csv (one row per control step) and DIR/demo.png (payload height, top,
    /// and tilt, bottom, over time; grid every 5 s, 0.1 m and 1 degree).
    Demo {
        /// Payload: box, bricks or sledge.
        #[arg(long)]
        payload: PayloadKind,
        /// Seed of the env's random stream.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Nominal world: flat ground, mid-range friction, no command noise or joint offsets.
        #[arg(long)]
        no_randomization: bool,
        /// Output folder (created if missing).
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
        /// Simulator config.
        #[arg(long, default_value = "configs/sim.toml")]
        config: PathBuf,
    },
    /// Measure control and physics (integration) steps per second for one env and for a batch
    /// replaying the scripted mission's commands under domain randomization, and the accuracy
    /// of the configured solver settings against a fine reference.
    Bench {
        /// Print only the batched result as one JSON line.
        #[arg(long)]
        json: bool,
        /// Envs in the batch.
        #[arg(long, default_value_t = 64)]
        envs: usize,
        /// Worker threads (0: one per core).
        #[arg(long, default_value_t = 0)]
        threads: usize,
        /// Control steps per env (default: 10 s of the scripted mission).
        #[arg(long, default_value_t = 500)]
        steps: usize,
        /// Simulator config.
        #[arg(long, default_value = "configs/sim.toml")]
        config: PathBuf,
    },
}

pub fn run(cmd: SimCommand) -> Result<()> {
    match cmd {
        SimCommand::Demo {
            payload,
            seed,
            no_randomization,
            out,
            config,
        } => demo(payload, seed, !no_randomization, &out, &config),
        SimCommand::Bench {
            json,
            envs,
            threads,
            steps,
            config,
        } => bench(json, envs, threads, steps, &config),
    }
}

fn load_scene(config: &Path) -> Result<SceneModel> {
    let config = SimConfig::load(config)
        .with_context(|| format!("cannot load simulator config {}", config.display()))?;
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

fn demo(payload: PayloadKind, seed: u64, randomize: bool, out: &Path, config: &Path) -> Result<()> {
    let scene = load_scene(config)?;
    let options = EnvOptions {
        randomize,
        payload: Some(payload),
    };
    let mut env = Env::new(&scene, seed, options).context("cannot create the env")?;
    let mut rows = Vec::new();
    let summary = run_mission(&scene, &mut env, scene.config.mission, |phase, s| {
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
    write_atomically(&out.join("demo.csv"), |tmp| {
        std::fs::write(tmp, &csv).map_err(Into::into)
    })?;
    write_atomically(&out.join("demo.png"), |tmp| plot(tmp, &rows))?;
    println!(
        "{} ({}): max height {:.3} m, max tilt {:.2} deg, travel {:.3} m, touchdown {:.3} m/s, \
         max grasp force {:.1} N, grasp drift {:.2} mm / {:.3} deg, broken: {}",
        payload.name(),
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
    );
    println!(
        "wrote {} and {}",
        out.join("demo.csv").display(),
        out.join("demo.png").display()
    );
    Ok(())
}

/// Writes `path` whole or not at all ([`moonhaul_core::atomic_file`]).
fn write_atomically(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    let context = || format!("cannot write {}", path.display());
    moonhaul_core::atomic_file::write_with(
        path,
        |temp| write(temp).with_context(context),
        |e| anyhow::Error::new(e).context(context()),
    )
}

/// The bundled ASCII subset of DejaVu Sans (`assets/fonts/`, licence beside it), so labels
/// need no system font library.
static FONT: &[u8] = include_bytes!("../assets/fonts/DejaVuSans-ascii.ttf");

/// Two panels over mission time: payload height (m) on top, tilt (deg) below.
fn plot(path: &Path, rows: &[Row]) -> Result<()> {
    static REGISTERED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    let font_ok = *REGISTERED.get_or_init(|| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, FONT).is_ok()
    });
    anyhow::ensure!(font_ok, "the bundled font is invalid");
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
            .caption(title, ("sans-serif", 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..t_end, (lo - pad)..(hi + pad))?;
        chart
            .configure_mesh()
            .x_desc("mission time (s)")
            .y_desc(y_desc)
            .label_style(("sans-serif", 15))
            .axis_desc_style(("sans-serif", 16))
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
fn scripted_commands(scene: &SceneModel, steps: usize) -> Result<Vec<[UnitCommand; UNITS]>> {
    let mut env = Env::new(
        scene,
        0,
        EnvOptions {
            randomize: false,
            payload: None,
        },
    )?;
    let mut state = env.state(scene);
    let mut controller = ScriptedController::new(scene.config.mission, scene, &state)?;
    let mut commands = Vec::with_capacity(steps);
    for _ in 0..steps {
        let (_, command) = controller.command(scene, state.time_s, &state)?;
        env.step(scene, &command);
        env.state_into(scene, &mut state);
        commands.push(command);
    }
    Ok(commands)
}

fn bench(json: bool, envs: usize, threads: usize, steps: usize, config: &Path) -> Result<()> {
    let scene = load_scene(config)?;
    let decimation = scene.decimation() as f64;
    let plan = scripted_commands(&scene, steps)?;
    let mut rates = Vec::new();
    for (count, threads) in [(1, 1), (envs, threads)] {
        if json && count == 1 {
            continue;
        }
        let mut batch = BatchEnv::new(scene.clone(), count, 1, EnvOptions::default(), threads)?;
        let mut commands = vec![plan[0]; count];
        let start = Instant::now();
        for step in &plan {
            commands.iter_mut().for_each(|c| *c = *step);
            batch.step(&commands)?;
        }
        let elapsed = start.elapsed().as_secs_f64();
        let control = (count * plan.len()) as f64 / elapsed;
        rates.push((count, batch.threads(), control, control * decimation));
    }
    let &(n, t, control, physics) = rates.last().context("no bench ran")?;
    if json {
        println!(
            "{}",
            serde_json::json!({"envs": n, "threads": t, "control_steps_per_s": control, "physics_steps_per_s": physics})
        );
        return Ok(());
    }
    let p = &scene.config.physics;
    println!(
        "config: {} Hz integration, {} Hz collision detection, {} Hz control, {} PGS sweep(s)",
        p.physics_hz, p.collision_hz, p.control_hz, p.num_internal_pgs_iterations
    );
    for (n, t, control, physics) in &rates {
        println!(
            "{n:>5} env(s) on {t} thread(s): {control:>9.0} control steps/s, {physics:>9.0} physics steps/s"
        );
    }
    let report = accuracy::compare(&scene).context("accuracy run failed")?;
    println!("{report}");
    Ok(())
}
