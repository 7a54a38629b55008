//! `cargo xtask train-all`: retrains the bundled phase policies and picks, among the seeds it
//! trains, the one that flies the most validation missions through the deployed stack.
//!
//! Why select at all: one place recipe, drawn with three seeds, completed 75 to 100 of 100
//! deployed sledge missions (docs/measurements/2026-12-07-episode-past-clock.md); a bundle that
//! is one draw of it is a lottery. The issue asks to select by deployed completion, not by
//! training return, so the score is missions completed by `moonhaul eval`'s deployed stack
//! (onboard tick, gate, pipeline, clamp). Validation missions are their own stream
//! (`configs/train/bundle.toml [validation] seed`), never the reported test missions
//! (`moonhaul eval`'s default seed 1000), and fly only training payloads, so the sledge and the
//! test crates stay unseen.
//!
//! The lift is judged first by its open-loop rows (`moonhaul eval`'s lift cases at the paper's
//! three heights): the deployed missions lift to one height (`configs/mission.toml`) and hand
//! over at the gate's test, so their completion cannot tell lift candidates apart by the
//! paper's lift accuracy (lift clones of one recipe and seed completed the same missions with
//! 3.9 and 11.6 mm of open-loop error at 0.3 m, docs/measurements/2026-12-07-sledge-failures.md).
//!
//! Phases are chosen in mission order, each flown with the phases already chosen before it and
//! the first-listed seed of those after it: a phase is judged with the partners it will be
//! bundled with wherever they are known.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use serde::Deserialize;

use crate::{cargo_command, run, setup, with_run_moonhaul, workspace_root};

/// The bundled phases, in mission order.
const PHASES: [&str; 3] = ["lift", "transport", "place"];

const CONFIG: &str = "configs/train/bundle.toml";

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct BundleConfig {
    validation: Validation,
    seeds: Seeds,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Validation {
    payloads: Vec<String>,
    episodes: u32,
    seed: u64,
    lift_min_success_rate: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Seeds {
    lift: Vec<u64>,
    transport: Vec<u64>,
    place: Vec<u64>,
}

impl Seeds {
    fn of(&self, phase: &str) -> &[u64] {
        match phase {
            "lift" => &self.lift,
            "transport" => &self.transport,
            _ => &self.place,
        }
    }
}

impl BundleConfig {
    fn parse(text: &str, file: &str) -> Result<Self, String> {
        let config: BundleConfig = toml::from_str(text).map_err(|e| format!("{file}: {e}"))?;
        for phase in PHASES {
            let seeds = config.seeds.of(phase);
            if seeds.is_empty() {
                return Err(format!(
                    "{file}: seeds.{phase} is empty: give at least one seed"
                ));
            }
            if let Some(s) = seeds
                .iter()
                .enumerate()
                .find_map(|(i, s)| seeds[..i].contains(s).then_some(s))
            {
                return Err(format!("{file}: seeds.{phase} lists seed {s} twice"));
            }
        }
        let v = &config.validation;
        if !(1..=10_000).contains(&v.episodes) {
            return Err(format!(
                "{file}: validation.episodes = {} must be 1 to 10000",
                v.episodes
            ));
        }
        if !(0.0..=1.0).contains(&v.lift_min_success_rate) {
            return Err(format!(
                "{file}: validation.lift_min_success_rate = {} must be 0 to 1",
                v.lift_min_success_rate
            ));
        }
        if v.payloads.is_empty() {
            return Err(format!("{file}: validation.payloads is empty"));
        }
        if let Some(p) = v
            .payloads
            .iter()
            .find(|p| p.trim().is_empty() || p.contains(','))
        {
            return Err(format!(
                "{file}: validation.payloads holds {p:?}: one payload name or URDF path per entry"
            ));
        }
        Ok(config)
    }
}

/// One candidate's validation: missions completed per payload, in `validation.payloads` order,
/// and for a lift candidate its open-loop accuracy.
#[derive(Debug, Clone, PartialEq)]
struct Score {
    seed: u64,
    completed: Vec<u32>,
    lift: Option<LiftAccuracy>,
}

/// A lift candidate's open-loop rows (every validation payload at every height the report
/// holds) against the paper's final height errors.
#[derive(Debug, Clone, PartialEq)]
struct LiftAccuracy {
    /// Rows whose mean final error is within the paper's and whose success rate reaches
    /// `validation.lift_min_success_rate`.
    rows_met: u32,
    rows: u32,
    /// Σ over rows of mean error / the paper's error: the tie-break, lower is better.
    error_over_paper: f64,
}

impl Score {
    fn total(&self) -> u32 {
        self.completed.iter().sum()
    }

    fn worst(&self) -> u32 {
        self.completed.iter().copied().min().unwrap_or(0)
    }
}

/// The best candidate: for the lift the most open-loop rows within the paper's; then the most
/// missions completed in all, then the best worst payload; then for the lift the smallest
/// error against the paper's; then the earlier-listed seed.
fn best(scores: &[Score]) -> Option<&Score> {
    let key = |s: &Score| {
        let (met, error) = s
            .lift
            .as_ref()
            .map_or((0, 0.0), |l| (l.rows_met, l.error_over_paper));
        (met, s.total(), s.worst(), -error)
    };
    scores.iter().reduce(|best, s| {
        if key(s).partial_cmp(&key(best)) == Some(std::cmp::Ordering::Greater) {
            s
        } else {
            best
        }
    })
}

/// The open-loop lift rows of `moonhaul eval --json` (the learned policies'; the scripted ones
/// are under `scripted`): `<payload>.lift.<height>`'s
/// `final_height_error_mm` (its `mean` and the `paper` figure eval prints beside it) and
/// `success_rate.mean`.
fn lift_accuracy(
    report: &serde_json::Value,
    payloads: &[String],
    min_success_rate: f64,
) -> Result<LiftAccuracy, String> {
    let mut accuracy = LiftAccuracy {
        rows_met: 0,
        rows: 0,
        error_over_paper: 0.0,
    };
    for p in payloads {
        let name = report_name(p);
        let rows = report
            .pointer(&format!("/{name}/lift"))
            .and_then(serde_json::Value::as_object)
            .filter(|rows| !rows.is_empty())
            .ok_or_else(|| format!("moonhaul eval's report has no {name}.lift rows"))?;
        for (height, row) in rows {
            let number = |path: &str| {
                row.pointer(path)
                    .and_then(serde_json::Value::as_f64)
                    .ok_or_else(|| {
                        format!(
                            "moonhaul eval's report has no {name}.lift.{height}{}",
                            path.replace('/', ".")
                        )
                    })
            };
            let error = number("/final_height_error_mm/mean")?;
            let paper = number("/final_height_error_mm/paper")?;
            let success = number("/success_rate/mean")?;
            accuracy.rows += 1;
            accuracy.rows_met += u32::from(error <= paper && success >= min_success_rate);
            accuracy.error_over_paper += error / paper;
        }
    }
    Ok(accuracy)
}

/// `moonhaul eval --json`'s stdout as JSON.
fn parse_report(stdout: &str) -> Result<serde_json::Value, String> {
    serde_json::from_str(stdout.trim())
        .map_err(|e| format!("moonhaul eval --json printed no JSON report: {e}"))
}

/// The name `moonhaul eval` reports a payload under: a URDF by its file stem.
fn report_name(payload: &str) -> &str {
    Path::new(payload)
        .file_stem()
        .map_or(payload, |s| s.to_str().unwrap_or(payload))
}

/// Missions completed per payload, from `moonhaul eval --json`'s
/// `<payload>.learned.deployed.clamp.completed_rate`.
fn completed_missions(
    report: &serde_json::Value,
    payloads: &[String],
    episodes: u32,
) -> Result<Vec<u32>, String> {
    payloads
        .iter()
        .map(|p| {
            let name = report_name(p);
            let rate = report
                .pointer(&format!("/{name}/learned/deployed/clamp/completed_rate"))
                .and_then(serde_json::Value::as_f64)
                .ok_or_else(|| {
                    format!("moonhaul eval's report has no {name}.learned.deployed.clamp.completed_rate")
                })?;
            Ok((rate * f64::from(episodes)).round() as u32)
        })
        .collect()
}

/// Retrains every phase with every listed seed, selects one per phase by validation missions
/// (where more than one seed is listed), and bundles it into `assets/policies/`, with
/// `selection.json` recording every candidate's score.
///
/// With `keep_trained` (`--keep-trained`, to finish a run that stopped after training), a seed
/// whose run directory already holds its `policy.safetensors` is not trained again, and an
/// existing hand-over capture is kept; `selection.json` lists what was kept, and the phases'
/// wall times then count only what ran.
pub fn train_all(keep_trained: bool) -> Result<(), String> {
    let root = workspace_root();
    let config_path = root.join(CONFIG);
    let text = std::fs::read_to_string(&config_path)
        .map_err(|e| format!("cannot read {}: {e}", config_path.display()))?;
    let config = BundleConfig::parse(&text, CONFIG)?;
    let venv = setup()?;
    // One package per build, as each is run below: built together, cargo unifies their
    // features and the first `cargo run` of either rebuilds it (minutes on 2 cores, counted in
    // a phase's wall time).
    for (package, bin) in [
        ("moonhaul-learn", "moonhaul-train"),
        ("moonhaul", "moonhaul"),
    ] {
        run(cargo_command(&venv).args(["build", "--release", "--package", package, "--bin", bin]))?;
    }
    // Transport and place mix in worlds that start where the scripted expert handed over
    // through the deployed stack (their configs' `[world] handovers`).
    let handovers = "runs/handovers/scripted.json";
    let mut kept = Vec::new();
    if keep_trained && root.join(handovers).is_file() {
        kept.push(handovers.to_string());
    } else {
        run(moonhaul(&venv).args(["sim", "handovers", "--out", handovers, "--force"]))?;
    }
    let run_dir = |phase: &str, seed: u64| {
        root.join("runs")
            .join(format!("{phase}-warm"))
            .join(format!("seed-{seed}"))
    };
    let mut phase_s = [0.0f64; 3];
    for (k, phase) in PHASES.into_iter().enumerate() {
        for &seed in config.seeds.of(phase) {
            let started = Instant::now();
            let out = run_dir(phase, seed);
            if keep_trained && out.join("policy.safetensors").is_file() {
                eprintln!("xtask: {phase} seed {seed}: kept {}", out.display());
                kept.push(format!("{phase} seed {seed}"));
                continue;
            }
            // The cloned expert: DAgger and the critic's warm-up, no PPO. PPO from the clone
            // has not yet flown more missions through the deployed stack than the clone itself
            // (docs/measurements/2026-12-04.md), so the bundle is the clone.
            run(cargo_command(&venv)
                .args(["run", "--quiet", "--release"])
                .args([
                    "--package",
                    "moonhaul-learn",
                    "--bin",
                    "moonhaul-train",
                    "--",
                ])
                .arg("--config")
                .arg(format!("configs/train/{phase}_warm.toml"))
                .arg("--seed")
                .arg(seed.to_string())
                .args(["--iterations", "0", "--out"])
                .arg(&out))?;
            phase_s[k] += started.elapsed().as_secs_f64();
        }
    }
    // Chosen seeds, the first listed until a phase's validation picks.
    let mut chosen: Vec<u64> = PHASES.iter().map(|p| config.seeds.of(p)[0]).collect();
    let mut selection = serde_json::Map::new();
    for (k, phase) in PHASES.into_iter().enumerate() {
        let seeds = config.seeds.of(phase);
        if seeds.len() == 1 {
            continue;
        }
        let started = Instant::now();
        let mut scores = Vec::new();
        for &seed in seeds {
            let team = root
                .join("runs")
                .join("train-all-validation")
                .join(format!("{phase}-seed-{seed}"));
            std::fs::create_dir_all(&team)
                .map_err(|e| format!("cannot create {}: {e}", team.display()))?;
            for (j, other) in PHASES.into_iter().enumerate() {
                let from_seed = if j == k { seed } else { chosen[j] };
                copy(
                    &run_dir(other, from_seed).join("policy.safetensors"),
                    &team.join(format!("{other}.safetensors")),
                )?;
            }
            let v = &config.validation;
            let mut eval = moonhaul(&venv);
            eval.arg("eval")
                .arg("--policies")
                .arg(&team)
                .args(["--no-scripted", "--json", "--payload"])
                .arg(v.payloads.join(","))
                .arg("--episodes")
                .arg(v.episodes.to_string())
                .arg("--seed")
                .arg(v.seed.to_string());
            let report = parse_report(&output(&mut eval)?)?;
            let completed = completed_missions(&report, &v.payloads, v.episodes)?;
            let lift = (phase == "lift")
                .then(|| lift_accuracy(&report, &v.payloads, v.lift_min_success_rate))
                .transpose()?;
            eprintln!(
                "xtask: {phase} seed {seed}: {} of {} validation missions completed ({}){}",
                completed.iter().sum::<u32>(),
                v.episodes as usize * v.payloads.len(),
                v.payloads
                    .iter()
                    .zip(&completed)
                    .map(|(p, c)| format!("{p} {c}"))
                    .collect::<Vec<_>>()
                    .join(", "),
                lift.as_ref().map_or(String::new(), |l| format!(
                    "; open-loop lift: {} of {} rows within the paper's error, error / paper summed {:.2}",
                    l.rows_met, l.rows, l.error_over_paper
                ))
            );
            scores.push(Score {
                seed,
                completed,
                lift,
            });
        }
        let pick = best(&scores).expect("seeds are never empty (checked)");
        chosen[k] = pick.seed;
        selection.insert(
            phase.into(),
            serde_json::json!({
                "chosen_seed": pick.seed,
                "partners": PHASES.iter().zip(&chosen).filter(|(p, _)| **p != phase)
                    .map(|(p, s)| (p.to_string(), serde_json::json!(s)))
                    .collect::<serde_json::Map<_, _>>(),
                "candidates": scores.iter().map(|s| {
                    let mut c = serde_json::json!({
                        "seed": s.seed,
                        "completed": config.validation.payloads.iter().zip(&s.completed)
                            .map(|(p, c)| (p.clone(), serde_json::json!(c)))
                            .collect::<serde_json::Map<_, _>>(),
                    });
                    if let Some(l) = &s.lift {
                        c["open_loop_lift"] = serde_json::json!({
                            "rows_within_paper": l.rows_met,
                            "rows": l.rows,
                            "error_over_paper": l.error_over_paper,
                        });
                    }
                    c
                }).collect::<Vec<_>>(),
            }),
        );
        phase_s[k] += started.elapsed().as_secs_f64();
    }
    let assets = root.join("assets").join("policies");
    std::fs::create_dir_all(&assets)
        .map_err(|e| format!("cannot create {}: {e}", assets.display()))?;
    for (k, phase) in PHASES.into_iter().enumerate() {
        let out = run_dir(phase, chosen[k]);
        copy(
            &out.join("policy.safetensors"),
            &assets.join(format!("{phase}.safetensors")),
        )?;
        copy(
            &out.join("metrics.csv"),
            &assets.join(format!("{phase}.metrics.csv")),
        )?;
        eprintln!(
            "xtask: {phase} policy (seed {}) bundled in {}; {} seed(s) trained{} in {:.1} min",
            chosen[k],
            assets.display(),
            config.seeds.of(phase).len(),
            if config.seeds.of(phase).len() > 1 {
                " and validated"
            } else {
                ""
            },
            phase_s[k] / 60.0
        );
    }
    let record = serde_json::json!({
        "config": CONFIG,
        "validation": {
            "payloads": config.validation.payloads,
            "episodes": config.validation.episodes,
            "seed": config.validation.seed,
            "lift_min_success_rate": config.validation.lift_min_success_rate,
        },
        "seeds": PHASES.iter().zip(&chosen)
            .map(|(p, s)| (p.to_string(), serde_json::json!(s)))
            .collect::<serde_json::Map<_, _>>(),
        "selection": selection,
        "kept_from_an_earlier_run": kept,
        "wall_time_s": PHASES.iter().zip(phase_s)
            .map(|(p, s)| (p.to_string(), serde_json::json!(s.round())))
            .collect::<serde_json::Map<_, _>>(),
    });
    let path = assets.join("selection.json");
    let text = serde_json::to_string_pretty(&record).expect("plain JSON values") + "\n";
    write_atomically(&path, &text)
}

/// `moonhaul` (release, built above) as a command in the workspace root.
fn moonhaul(venv: &Path) -> Command {
    let mut command = cargo_command(venv);
    with_run_moonhaul(&mut command);
    command
}

/// Runs `command`, its stderr shown, and returns its stdout.
fn output(command: &mut Command) -> Result<String, String> {
    let out = command
        .stderr(std::process::Stdio::inherit())
        .output()
        .map_err(|e| format!("cannot start {:?}: {e}", command.get_program()))?;
    if !out.status.success() {
        return Err(format!(
            "{:?} failed ({})",
            command.get_args().collect::<Vec<_>>(),
            out.status
        ));
    }
    String::from_utf8(out.stdout).map_err(|e| format!("moonhaul eval printed non-UTF-8: {e}"))
}

fn copy(from: &Path, to: &Path) -> Result<(), String> {
    std::fs::copy(from, to)
        .map(drop)
        .map_err(|e| format!("cannot copy {} to {}: {e}", from.display(), to.display()))
}

/// Writes through a temporary file beside `path`, so a killed run leaves the old file or the new.
fn write_atomically(path: &Path, text: &str) -> Result<(), String> {
    let tmp = PathBuf::from(format!("{}.tmp", path.display()));
    std::fs::write(&tmp, text)
        .and_then(|()| std::fs::rename(&tmp, path))
        .map_err(|e| format!("cannot write {}: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    const SHIPPED: &str = include_str!("../../configs/train/bundle.toml");

    #[test]
    fn the_shipped_config_parses() {
        let c = BundleConfig::parse(SHIPPED, CONFIG).unwrap();
        assert!(PHASES.iter().all(|p| !c.seeds.of(p).is_empty()));
    }

    #[test]
    fn a_bad_config_is_refused_naming_the_field() {
        let good = "[validation]\npayloads = [\"box\"]\nepisodes = 10\nseed = 5\n\
                    lift_min_success_rate = 0.95\n\
                    [seeds]\nlift = [1]\ntransport = [1]\nplace = [1, 2]\n";
        assert!(BundleConfig::parse(good, "b.toml").is_ok());
        for (bad, field) in [
            (good.replace("place = [1, 2]", "place = []"), "seeds.place"),
            (
                good.replace("place = [1, 2]", "place = [2, 2]"),
                "seeds.place",
            ),
            (
                good.replace("episodes = 10", "episodes = 0"),
                "validation.episodes",
            ),
            (good.replace("[\"box\"]", "[]"), "validation.payloads"),
            (
                good.replace("[\"box\"]", "[\"box,bricks\"]"),
                "validation.payloads",
            ),
            (good.replace("seed = 5", "seed = 5\nextra = 1"), "extra"),
            (
                good.replace("= 0.95", "= 95"),
                "validation.lift_min_success_rate",
            ),
            (good.replace("lift = [1]\n", ""), "lift"),
        ] {
            let e = BundleConfig::parse(&bad, "b.toml").unwrap_err();
            assert!(e.contains("b.toml") && e.contains(field), "{field}: {e}");
        }
    }

    #[test]
    fn the_best_seed_completes_most_then_has_the_best_worst_payload_then_comes_first() {
        let s = |seed, completed: &[u32]| Score {
            seed,
            completed: completed.to_vec(),
            lift: None,
        };
        assert_eq!(best(&[s(1, &[48, 47]), s(2, &[50, 49])]).unwrap().seed, 2);
        assert_eq!(best(&[s(1, &[50, 44]), s(2, &[47, 47])]).unwrap().seed, 2);
        assert_eq!(best(&[s(3, &[47, 47]), s(1, &[47, 47])]).unwrap().seed, 3);
        // A lift is judged by its open-loop rows first, its error last.
        let lift = |seed, completed: &[u32], rows_met, error_over_paper| Score {
            lift: Some(LiftAccuracy {
                rows_met,
                rows: 6,
                error_over_paper,
            }),
            ..s(seed, completed)
        };
        let fewer_rows = lift(1, &[50, 50], 5, 2.0);
        let more_rows = lift(2, &[49, 48], 6, 3.0);
        assert_eq!(best(&[fewer_rows, more_rows.clone()]).unwrap().seed, 2);
        let closer = lift(3, &[49, 48], 6, 2.5);
        assert_eq!(best(&[more_rows, closer]).unwrap().seed, 3);
    }

    #[test]
    fn lift_rows_are_judged_against_the_paper_figure_eval_reports() {
        let row = |error: f64, paper: f64, success: f64| {
            serde_json::json!({
                "final_height_error_mm": {"mean": error, "sd": 1.0, "paper": paper},
                "success_rate": {"mean": success, "sd": 0.0},
            })
        };
        let report = serde_json::json!({
            "box": {"lift": {"0.3": row(5.0, 5.9, 1.0), "0.5": row(18.0, 17.4, 1.0)},
                    "scripted": {"lift": {"0.3": row(1.0, 5.9, 1.0)}}},
            "bricks": {"lift": {"0.3": row(2.95, 5.9, 0.9)}},
        });
        let payloads = ["box".to_string(), "bricks".to_string()];
        let a = lift_accuracy(&report, &payloads, 0.95).unwrap();
        assert_eq!((a.rows_met, a.rows), (1, 3));
        let expected = 5.0 / 5.9 + 18.0 / 17.4 + 0.5;
        assert!((a.error_over_paper - expected).abs() < 1e-12, "{a:?}");
        assert_eq!(lift_accuracy(&report, &payloads, 0.9).unwrap().rows_met, 2);
        let e = lift_accuracy(&report, &["sledge".to_string()], 0.95).unwrap_err();
        assert!(e.contains("sledge.lift"), "{e}");
        let no_paper = parse_report(&report.to_string().replace("\"paper\":5.9,", "")).unwrap();
        let e = lift_accuracy(&no_paper, &payloads, 0.95).unwrap_err();
        assert!(e.contains("final_height_error_mm.paper"), "{e}");
    }

    #[test]
    fn completed_missions_are_read_from_the_eval_report_by_payload_name() {
        let report = r#"{"box":{"learned":{"deployed":{"clamp":{"completed_rate":0.96}}}},
            "payload_long_heavy":{"learned":{"deployed":{"clamp":{"completed_rate":0.5}}}}}"#;
        let payloads = [
            "box".to_string(),
            "tests/data/payload_long_heavy.urdf".to_string(),
        ];
        let report = parse_report(report).unwrap();
        assert_eq!(
            completed_missions(&report, &payloads, 50).unwrap(),
            [48, 25]
        );
        let e = completed_missions(&report, &["bricks".to_string()], 50).unwrap_err();
        assert!(
            e.contains("bricks.learned.deployed.clamp.completed_rate"),
            "{e}"
        );
        assert!(parse_report("progress\n").is_err());
    }
}
