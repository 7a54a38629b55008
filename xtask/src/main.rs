//! `cargo xtask`: the project's set-up and the README's two commands.
//!
//! - `cargo xtask demo`  — the main job.
//! - `cargo xtask test`  — every test in the workspace.
//! - `cargo xtask setup` — only the set-up both of them do first.
//! - `cargo xtask train-all` — retrain the bundled phase policies (the expert's clones).
//! - `cargo xtask bench [ARGS…]` — moonhaul beside MuJoCo and rsl_rl, alternating, as ratios.
//! - `cargo xtask cargo ARGS…` — any cargo command with libtorch configured (clippy, bench, run).
//! - `cargo xtask vendor-check` — `vendor/*` are their crates.io releases plus `moonhaul.patch`
//!   (see `vendor_check.rs`; CI runs it).
//!
//! Set-up means libtorch for `moonhaul-learn`: PyTorch from PyPI (the exact version `tch`
//! links) in a project-local venv, installed once and reused. torch-sys finds it through
//! `LIBTORCH_USE_PYTORCH=1` and the venv's `python`; `moonhaul-learn`'s build script embeds its
//! library directory as an rpath, so nothing needs `LD_LIBRARY_PATH`.
//!
//! The same venv gets the Python trainer path: stock rsl_rl (pinned) and the `moonhaul` Python
//! package (`crates/py`, the phase environments as an rsl_rl `VecEnv`), built with maturin
//! from this checkout in release mode and installed editable, so `python -m moonhaul.train`
//! works in the venv after `cargo xtask setup`; `cargo xtask test` runs its pytest suite after
//! the Rust tests.
//!
//! `MOONHAUL_VENV` overrides the venv location (CI keeps one outside the clone). The tests also
//! get a small second venv with the pinned ROS 2 tooling (`rosbags`, `eclipse-zenoh`; a few MB),
//! `MOONHAUL_ROS2_VENV` or `.venv-ros2/`, whose python they find in `MOONHAUL_ROS2_PYTHON`.

use std::env;
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};
use std::time::Instant;

mod train_all;
mod vendor_check;

/// The PyTorch release `tch` 0.26 is built against.
const TORCH_VERSION: &str = "2.13.0";

/// The ROS 2 tooling the tests check moonhaul's bags and live topics with, pure Python (no ROS
/// install): rosbags (rosbag2 reader, CDR codec, Jazzy type store) and zenoh's Python API at
/// the zenoh release moonhaul links.
const ROS2_TEST_PACKAGES: [&str; 2] = ["rosbags==0.11.9", "eclipse-zenoh==1.10.2"];

/// The Python trainer path, beside PyTorch in the project venv: the rsl_rl release
/// `crates/py/python/moonhaul/rsl.py` is written against, its TensorDict, the extension's
/// builder and the test runner, all pinned.
const PYTHON_PACKAGES: [&str; 4] = [
    "rsl-rl-lib==5.5.1",
    "tensordict==0.15.3",
    "maturin==1.16.0",
    "pytest==9.2.0",
];

const USAGE: &str =
    "usage: cargo xtask <demo|test|setup|train-all [--keep-trained]|bench|vendor-check|cargo ARGS...>

  demo          run the main job: lift, transport and place a payload in simulation with
                two wheel-arm units (the learned phase policies through gate and clamp), and
                bring up a unit's CAN drives (emulated); see runs/demo/
  test [ARGS]   run every test: the workspace's, then the Python package's (crates/py/tests,
                pytest); extra ARGS go to `cargo test` and skip the Python tests
  setup         only the set-up: PyTorch from PyPI (libtorch for moonhaul-learn), stock
                rsl_rl and the `moonhaul` Python package (built from crates/py) into the
                project venv, .venv or MOONHAUL_VENV
  train-all     retrain the bundled policies: capture the scripted expert's hand-overs
                (runs/handovers/scripted.json), clone the expert into lift, transport and
                place with configs/train/<phase>_warm.toml's warm start (no PPO), once per
                seed configs/train/bundle.toml lists, into runs/<phase>-warm/seed-<S>/; where
                a phase lists several seeds, fly each through the deployed stack on the
                validation missions and keep the one that completes the most; copy each
                chosen policy and its training curve to assets/policies/ (selection.json
                records every candidate's score), printing each phase's wall time;
                --keep-trained finishes a run that stopped after training: seeds whose
                run folder holds a policy, and an existing capture, are kept
  bench [ARGS]  the side-by-side benchmark: the simulator against MuJoCo and the PPO update
                and act against rsl_rl 5.5.1, alternating, printing the ratios (installs
                mujoco and rsl_rl into a separate venv, MOONHAUL_BENCH_VENV or .venv-bench;
                ARGS go to bench/side_by_side.py, e.g. --rounds 5 --only sim)
  vendor-check  check that vendor/rapier3d and vendor/parry3d are their crates.io
                releases plus their moonhaul.patch (downloads each release once, cached
                under $CARGO_HOME/registry/cache/moonhaul-vendor-check/)
  cargo ARGS    run any cargo command with libtorch configured, e.g.
                `cargo xtask cargo clippy --workspace --all-targets -- -D warnings`";

fn main() -> ExitCode {
    let args: Vec<String> = env::args().skip(1).collect();
    let result = match args.first().map(String::as_str) {
        Some("demo") => demo(),
        Some("test") => test(&args[1..]),
        Some("setup") => setup().and_then(|venv| setup_python(&venv)),
        Some("train-all") => match &args[1..] {
            [] => train_all::train_all(false),
            [flag] if flag == "--keep-trained" => train_all::train_all(true),
            _ => Err(USAGE.to_owned()),
        },
        Some("bench") => bench(&args[1..]),
        Some("vendor-check") => vendor_check::vendor_check(),
        Some("cargo") => setup().and_then(|venv| cargo(&venv, &args[1..])),
        Some("-h" | "--help" | "help") => {
            println!("{USAGE}");
            Ok(())
        }
        _ => Err(USAGE.to_owned()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("xtask: {message}");
            ExitCode::FAILURE
        }
    }
}

fn workspace_root() -> PathBuf {
    // xtask/ lives directly under the workspace root. `cargo run` passes the manifest dir at
    // run time too; prefer it, so a binary built from another checkout sharing the target
    // directory still works on this one.
    env::var_os("CARGO_MANIFEST_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."))
}

fn venv_dir() -> PathBuf {
    env::var_os("MOONHAUL_VENV")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root().join(".venv"))
}

/// Creates the venv and installs PyTorch unless a previous run completed it.
fn setup() -> Result<PathBuf, String> {
    let venv = venv_dir();
    let torch = format!("torch=={TORCH_VERSION}");
    ensure_venv(
        &venv,
        &[&torch],
        &format!(".moonhaul-torch-{TORCH_VERSION}"),
    )?;
    Ok(venv)
}

/// Installs stock rsl_rl into `venv` (which [`setup`] made) and builds and installs the
/// `moonhaul` Python package from `crates/py` (release; cargo's incremental build makes a
/// repeat quick).
fn setup_python(venv: &Path) -> Result<(), String> {
    ensure_venv(venv, &PYTHON_PACKAGES, ".moonhaul-python")?;
    stage(
        "building the moonhaul Python package (crates/py) into the venv (first time: a \
         release build of the simulator, minutes on 2 cores)",
        || {
            // maturin runs cargo with the venv's python for pyo3's build script.
            run(Command::new(venv.join("bin").join("maturin"))
                .current_dir(workspace_root().join("crates").join("py"))
                .env("VIRTUAL_ENV", venv)
                .env("PATH", path_with_venv(venv))
                .args(["develop", "--release", "--quiet"]))
        },
    )
}

/// Creates `venv` and pip-installs `packages` unless a previous run completed exactly that: the
/// `stamp` file, holding the package list, is written only after pip succeeded, so an
/// interrupted install is retried and a changed list reinstalled.
fn ensure_venv(venv: &Path, packages: &[&str], stamp: &str) -> Result<(), String> {
    let python = venv.join("bin").join("python");
    let stamp = venv.join(stamp);
    let wanted = packages.join(" ");
    if std::fs::read_to_string(&stamp).is_ok_and(|s| s.trim() == wanted) {
        return Ok(());
    }
    if !python.exists() {
        eprintln!("xtask: creating Python venv at {}", venv.display());
        run(Command::new("python3").arg("-m").arg("venv").arg(venv)).map_err(|e| {
            format!("{e}\n(needs python3 with the venv module; on Debian: apt-get install python3-venv)")
        })?;
    }
    stage(
        &format!(
            "installing {wanted} from PyPI into {} (once: a download of several GB, minutes on \
             a fast link)",
            venv.display()
        ),
        || {
            run(Command::new(&python)
                .args(["-m", "pip", "install", "--disable-pip-version-check"])
                .args(packages))
        },
    )?;
    std::fs::write(&stamp, &wanted).map_err(|e| format!("cannot write {}: {e}", stamp.display()))
}

/// A `cargo` command with the environment torch-sys needs to find the venv's libtorch.
fn cargo_command(venv: &Path) -> Command {
    let cargo = env::var_os("CARGO").unwrap_or_else(|| OsString::from("cargo"));
    let mut command = Command::new(cargo);
    command
        .current_dir(workspace_root())
        .env("LIBTORCH_USE_PYTORCH", "1")
        .env("VIRTUAL_ENV", venv)
        .env("PATH", path_with_venv(venv));
    command
}

/// `PATH` with the venv's `bin/` first: its `python` is the one builds and tests find.
fn path_with_venv(venv: &Path) -> OsString {
    let mut path = OsString::from(venv.join("bin"));
    if let Some(old) = env::var_os("PATH") {
        path.push(":");
        path.push(old);
    }
    path
}

fn cargo(venv: &Path, args: &[String]) -> Result<(), String> {
    run(cargo_command(venv).args(args))
}

/// Creates the ROS 2 tooling venv unless a previous run completed it; returns its python.
fn setup_ros2() -> Result<PathBuf, String> {
    let venv = env::var_os("MOONHAUL_ROS2_VENV")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root().join(".venv-ros2"));
    ensure_venv(&venv, &ROS2_TEST_PACKAGES, ".moonhaul-ros2")?;
    Ok(venv.join("bin").join("python"))
}

fn test(extra: &[String]) -> Result<(), String> {
    let venv = setup()?;
    setup_python(&venv)?;
    let ros2_python = setup_ros2()?;
    stage(
        "building and running every test of the workspace (the first build compiles the \
         whole workspace with libtorch: 10-20 min on 2 cores, much less after)",
        || {
            // The ROS 2 tests fail, not skip, without their python under xtask.
            run(cargo_command(&venv)
                .env("MOONHAUL_ROS2_PYTHON", &ros2_python)
                .env("MOONHAUL_XTASK_TEST", "1")
                .args(["test", "--workspace"])
                .args(extra))
        },
    )?;
    if !extra.is_empty() {
        eprintln!(
            "xtask: arguments given, so only `cargo test`; the Python tests run without them"
        );
        return Ok(());
    }
    // The Python trainer path against the extension setup_python built: (a)-(c) of the
    // torchrun checks, a pendulum run that learns, the export to a policy file, which the
    // moonhaul binary the Rust tests just built must read.
    let target = env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root().join("target"));
    stage(
        "running the Python package's tests (crates/py/tests: torchrun with 2 processes, \
         about a minute)",
        || {
            run(Command::new(venv.join("bin").join("python"))
                .current_dir(workspace_root())
                .env("PATH", path_with_venv(&venv))
                .env("MOONHAUL_XTASK_TEST", "1")
                .env("MOONHAUL_BIN", target.join("debug").join("moonhaul"))
                .args(["-m", "pytest", "-q", "crates/py/tests"]))
        },
    )
}

/// Runs one long step of a command, saying first what it is and how long it roughly takes,
/// and afterwards how long it took: a first run on a fresh machine is never silent.
fn stage(what: &str, step: impl FnOnce() -> Result<(), String>) -> Result<(), String> {
    eprintln!("xtask: {what} ...");
    let started = Instant::now();
    let result = step();
    let took = started.elapsed().as_secs_f64();
    match &result {
        Ok(()) => eprintln!("xtask: done in {took:.0} s"),
        Err(_) => eprintln!("xtask: failed after {took:.0} s"),
    }
    result
}

/// The main job: the whole mission in simulation (flown by the scripted controller), the unit
/// model it runs on, and a unit's CAN start-up against
/// emulated drives. Everything lands in `runs/demo/`.
fn demo() -> Result<(), String> {
    // No libtorch: the onboard stack and the simulator are pure Rust, so plain cargo, no venv.
    let cargo = env::var_os("CARGO").unwrap_or_else(|| OsString::from("cargo"));
    let root = workspace_root();
    // cargo's own progress (its "Compiling" lines and bar) shows where the build is.
    stage(
        "building moonhaul and moonhaul-unit in release mode (a fresh machine compiles about \
         340 crates: 6-15 min on 2 cores; seconds once built)",
        || {
            run(Command::new(&cargo).current_dir(&root).args([
                "build",
                "--release",
                "--package",
                "moonhaul",
                "--bins",
            ]))
        },
    )?;
    let out = root.join("runs").join("demo");
    let out = out.to_string_lossy();
    let moonhaul =
        |args: &[&str]| run(with_run_moonhaul(Command::new(&cargo).current_dir(&root)).args(args));
    eprintln!("xtask: checking the unit model assets/unit.urdf");
    moonhaul(&["urdf", "check", "assets/unit.urdf"])?;
    // The mission: three payloads, three trials each, as the paper flew them; every unit its
    // own process on the sim-backed drives, peers and operator over zenoh, flying the bundled
    // phase policies (assets/policies/) through the phase gate, the action pipeline and the
    // clamp; each trial's controller is in summary.json (`trials[].controller`).
    stage(
        "the mission in simulation: 3 payloads x 3 trials, one world and two unit processes \
         each, every trial up to 90 s of simulated time (each prints when it starts and ends)",
        || {
            moonhaul(&[
                "mission",
                "sim",
                "--controller",
                "learned",
                "--payload",
                "box,bricks,sledge",
                "--trials",
                "3",
                "--seed",
                "1",
                "--out",
                &out,
                // runs/demo/ is the demo's own folder: each run replaces the last one's files.
                "--force",
            ])
        },
    )?;
    eprintln!("xtask: a unit's CAN start-up against emulated drives (2 s)");
    let can_log = format!("{out}/can.log");
    moonhaul(&[
        "can",
        "emulate",
        "--unit",
        "configs/unit_can.toml",
        "--seconds",
        "2",
        "--record",
        &can_log,
        "--force",
    ])?;
    eprintln!(
        "xtask: mission logs (MCAP, open in Foxglove) under {out}/<payload>/trial-<k>/, the \
         summary in {out}/summary.json, the mission profile in {out}/mission_profile.png, CAN \
         traffic in {can_log}"
    );
    Ok(())
}

/// The yardsticks of `cargo xtask bench`, pinned: the versions the issue measured against.
const BENCH_PACKAGES: [&str; 4] = [
    "torch==2.13.0",
    "rsl-rl-lib==5.5.1",
    "mujoco==4.0.0",
    "numpy==2.4.6",
];

/// Builds both sides, prepares the yardsticks' venv, and runs bench/side_by_side.py.
fn bench(extra: &[String]) -> Result<(), String> {
    let venv = setup()?;
    let bench_venv = env::var_os("MOONHAUL_BENCH_VENV")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root().join(".venv-bench"));
    ensure_venv(&bench_venv, &BENCH_PACKAGES, ".moonhaul-bench")?;
    // Compile first, so no round times a build.
    run(cargo_command(&venv).args(["build", "--release", "--package", "moonhaul"]))?;
    run(cargo_command(&venv).args([
        "bench",
        "--no-run",
        "--package",
        "moonhaul-learn",
        "--bench",
        "ppo",
    ]))?;
    let python = bench_venv.join("bin").join("python");
    // The script runs cargo for our side: give it the environment libtorch needs.
    run(Command::new(&python)
        .current_dir(workspace_root())
        .envs(
            cargo_command(&venv)
                .get_envs()
                .filter_map(|(k, v)| Some((k, v?))),
        )
        .arg("bench/side_by_side.py")
        .arg("--python")
        .arg(&python)
        .args(extra))
}

/// `command` (a cargo) made `cargo run` of the release `moonhaul` binary; its arguments follow.
fn with_run_moonhaul(command: &mut Command) -> &mut Command {
    command.args([
        "run",
        "--quiet",
        "--release",
        "--package",
        "moonhaul",
        "--bin",
        "moonhaul",
        "--",
    ])
}

fn run(command: &mut Command) -> Result<(), String> {
    let status = command
        .status()
        .map_err(|e| format!("cannot start {:?}: {e}", command.get_program()))?;
    if status.success() {
        Ok(())
    } else {
        Err(format!("{:?} failed ({status})", command.get_program()))
    }
}
