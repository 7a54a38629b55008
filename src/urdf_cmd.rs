//! `moonhaul urdf`: inspect URDF robot models with moonhaul-core's kinematics: validate and
//! print the kinematic tree, or compute the pose of one link in another's frame.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use moonhaul_core::kinematics::{Joint, KinematicTree, Link, MotionKind};

#[derive(clap::Subcommand)]
pub enum UrdfCommand {
    /// Validate a URDF and print its kinematic tree (joint types, axes, limits), link masses,
    /// total mass and DOF count. Exits non-zero, naming the offending element, if it is invalid.
    Check {
        /// URDF file to read.
        file: PathBuf,
    },
    /// Print the pose of the tip link frame expressed in the base link frame.
    Fk {
        /// URDF file to read.
        file: PathBuf,
        /// Link whose frame the pose is expressed in.
        #[arg(long)]
        base: String,
        /// Link whose pose is computed.
        #[arg(long)]
        tip: String,
        /// Comma-separated joint values (rad or m), one per movable joint in chain order (from
        /// base up to the common ancestor, then down to tip), e.g. `--q -0.5,1.2`. May be
        /// omitted when the chain has no movable joints.
        #[arg(long, allow_hyphen_values = true, value_name = "Q1,Q2,...")]
        q: Option<String>,
        /// Print one JSON line {"translation":[x,y,z],"rotation_xyzw":[x,y,z,w]} (metres; unit
        /// quaternion with w >= 0) instead of the human-readable pose.
        #[arg(long)]
        json: bool,
    },
}

pub fn run(cmd: UrdfCommand) -> Result<()> {
    match cmd {
        UrdfCommand::Check { file } => check(&file),
        UrdfCommand::Fk {
            file,
            base,
            tip,
            q,
            json,
        } => fk(&file, &base, &tip, q.as_deref().unwrap_or(""), json),
    }
}

fn load(file: &Path) -> Result<KinematicTree> {
    KinematicTree::from_file(file).with_context(|| format!("invalid URDF {}", file.display()))
}

fn check(file: &Path) -> Result<()> {
    let tree = load(file)?;
    println!("robot \"{}\" ({})", tree.name(), file.display());
    print_subtree(&tree, tree.root(), 0)?;
    println!(
        "{} links, total mass {:.3} kg; {} joints, {} DOF",
        tree.links().len(),
        tree.total_mass(),
        tree.joints().len(),
        tree.dof()
    );
    Ok(())
}

/// Prints `link` at `depth`, then each child joint followed by its child's subtree.
fn print_subtree(tree: &KinematicTree, link: &Link, depth: usize) -> Result<()> {
    let indent = 4 * depth;
    println!("{:indent$}{} ({:.3} kg)", "", link.name, link.mass);
    for (joint, child) in tree.children(&link.name)? {
        println!("{:indent$}  joint {}", "", describe(joint));
        print_subtree(tree, child, depth + 1)?;
    }
    Ok(())
}

/// One line: name, type, axis and limits with their units.
fn describe(joint: &Joint) -> String {
    let Some(motion) = &joint.motion else {
        return format!("{}: fixed", joint.name);
    };
    let (position, effort, velocity) = match motion.kind {
        MotionKind::Revolute | MotionKind::Continuous => ("rad", "N·m", "rad/s"),
        MotionKind::Prismatic => ("m", "N", "m/s"),
    };
    let limits = &motion.limits;
    let range = if motion.kind == MotionKind::Continuous {
        "unlimited".to_owned()
    } else {
        format!(
            "lower {} {position}, upper {} {position}",
            limits.lower, limits.upper
        )
    };
    let axis = motion.axis;
    format!(
        "{}: {}, axis ({}, {}, {}), {range}, effort {} {effort}, velocity {} {velocity}",
        joint.name,
        joint.type_name(),
        axis.x,
        axis.y,
        axis.z,
        limits.effort,
        limits.velocity
    )
}

fn fk(file: &Path, base: &str, tip: &str, q: &str, json: bool) -> Result<()> {
    let tree = load(file)?;
    let chain = tree
        .chain(base, tip)
        .with_context(|| format!("in URDF {}", file.display()))?;
    let q = parse_joint_values(q)?;
    let pose = chain.forward(&q).with_context(|| {
        let names: Vec<_> = chain.joint_names().collect();
        format!(
            "--q needs one value per joint from {base} to {tip}, in order: [{}]",
            names.join(", ")
        )
    })?;
    let t = pose.translation.vector;
    // q and -q are the same rotation; report the one with w >= 0.
    let r = if pose.rotation.w < 0.0 {
        -pose.rotation.into_inner()
    } else {
        pose.rotation.into_inner()
    };
    let translation = [t.x, t.y, t.z];
    let rotation_xyzw = [r.i, r.j, r.k, r.w];
    if json {
        println!(
            r#"{{"translation":{},"rotation_xyzw":{}}}"#,
            serde_json::to_string(&translation)?,
            serde_json::to_string(&rotation_xyzw)?
        );
    } else {
        let (roll, pitch, yaw) = pose.rotation.euler_angles();
        println!("pose of {tip} in the {base} frame:");
        println!("  translation (m):     {}", fmt_values(&translation));
        println!("  quaternion (xyzw):   {}", fmt_values(&rotation_xyzw));
        println!("  rpy (rad):           {}", fmt_values(&[roll, pitch, yaw]));
    }
    Ok(())
}

fn fmt_values(values: &[f64]) -> String {
    let values: Vec<_> = values.iter().map(|v| format!("{v:.6}")).collect();
    values.join(" ")
}

/// Parses `--q`: comma-separated finite numbers; empty means no values.
fn parse_joint_values(q: &str) -> Result<Vec<f64>> {
    if q.trim().is_empty() {
        return Ok(Vec::new());
    }
    q.split(',')
        .enumerate()
        .map(|(i, entry)| match entry.trim().parse::<f64>() {
            Ok(value) if value.is_finite() => Ok(value),
            _ => bail!("--q entry {} ({:?}) is not a finite number", i + 1, entry),
        })
        .collect()
}
