//! `moonhaul urdf`: inspect URDF robot models with moonhaul-core's kinematics: validate and
//! print the kinematic tree, or compute the pose of one link in another's frame.

use std::collections::HashMap;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use moonhaul_core::kinematics::urdf_rs;
use moonhaul_core::kinematics::{
    principal_moments, read_urdf, Joint, KinematicTree, Link, MotionKind,
};

/// Deepest tree level printed with its own indentation; deeper levels (a long chain) keep this
/// indentation and print their depth instead, so output stays linear in the tree size.
const MAX_INDENT_LEVELS: usize = 16;

#[derive(clap::Subcommand)]
pub enum UrdfCommand {
    /// Validate a URDF and print its kinematic tree (joint types, axes, limits), link masses,
    /// inertias and geometry, total mass and DOF count. Checks structure and physics (finite
    /// values, non-negative masses, positive limits and sizes, positive semi-definite inertias
    /// obeying the triangle inequality). Exits non-zero, naming the file and the offending
    /// element, if the URDF is invalid.
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
        /// omitted when the chain has no movable joints. Each must lie within its joint's URDF
        /// position limits.
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

/// Reads and validates a URDF; every error names the file.
fn load(file: &Path) -> Result<(urdf_rs::Robot, KinematicTree)> {
    let robot = read_urdf(file)?;
    let tree =
        KinematicTree::from_robot(&robot).with_context(|| format!("URDF {}", file.display()))?;
    Ok((robot, tree))
}

fn check(file: &Path) -> Result<()> {
    let (robot, tree) = load(file)?;
    let mut out = BufWriter::new(std::io::stdout().lock());
    print_check(&mut out, file, &robot, &tree)
        .and_then(|()| out.flush().map_err(Into::into))
        .context("cannot write to stdout")
}

fn print_check(
    out: &mut impl Write,
    file: &Path,
    robot: &urdf_rs::Robot,
    tree: &KinematicTree,
) -> Result<()> {
    writeln!(out, "robot \"{}\" ({})", tree.name(), file.display())?;
    print_tree(out, robot, tree)?;
    writeln!(
        out,
        "{} links, total mass {:.3} kg; {} joints, {} DOF",
        tree.links().len(),
        tree.total_mass(),
        tree.joints().len(),
        tree.dof()
    )?;
    let inertials = robot.links.iter().filter(|l| has_inertial(l)).count();
    let visuals: usize = robot.links.iter().map(|l| l.visual.len()).sum();
    let collisions: usize = robot.links.iter().map(|l| l.collision.len()).sum();
    writeln!(
        out,
        "checked: {inertials} inertials (finite, mass > 0, inertia positive semi-definite and \
         within the triangle inequality), {} movable joints (finite position limits where they \
         apply, effort and velocity > 0 where given, dynamics >= 0), {collisions} collision and {visuals} visual geometries (finite, \
         sizes > 0)",
        tree.dof()
    )?;
    Ok(())
}

/// Prints the tree depth-first from the root, without recursion (a URDF may be a chain of
/// thousands of links): each link with its mass, inertia and geometry, each joint before the
/// subtree of its child.
fn print_tree(out: &mut impl Write, robot: &urdf_rs::Robot, tree: &KinematicTree) -> Result<()> {
    let urdf_links: HashMap<&str, &urdf_rs::Link> =
        robot.links.iter().map(|l| (l.name.as_str(), l)).collect();
    let mut stack: Vec<(Option<&Joint>, &Link, usize)> = vec![(None, tree.root(), 0)];
    while let Some((joint, link, depth)) = stack.pop() {
        let indent = 4 * depth.min(MAX_INDENT_LEVELS);
        if let Some(joint) = joint {
            let indent = 4 * (depth - 1).min(MAX_INDENT_LEVELS);
            writeln!(out, "{:indent$}  joint {}", "", describe(joint))?;
        }
        let level = if depth > MAX_INDENT_LEVELS {
            format!("[depth {depth}] ")
        } else {
            String::new()
        };
        writeln!(
            out,
            "{:indent$}{level}{} ({:.3} kg)",
            "", link.name, link.mass
        )?;
        if let Some(urdf_link) = urdf_links.get(link.name.as_str()) {
            for line in physical_lines(urdf_link) {
                writeln!(out, "{:indent$}  {line}", "")?;
            }
        }
        let children: Vec<_> = tree.children(&link.name)?.collect();
        for (joint, child) in children.into_iter().rev() {
            stack.push((Some(joint), child, depth + 1));
        }
    }
    Ok(())
}

/// Whether a link has an inertial to print: urdf_rs reads an absent `<inertial>` as all zeros.
fn has_inertial(link: &urdf_rs::Link) -> bool {
    let urdf_rs::Inertial {
        origin,
        mass,
        inertia,
    } = &link.inertial;
    let i = inertia;
    mass.value != 0.0
        || [i.ixx, i.ixy, i.ixz, i.iyy, i.iyz, i.izz]
            .iter()
            .chain(origin.xyz.iter())
            .chain(origin.rpy.iter())
            .any(|&v| v != 0.0)
}

/// The checked physical data of a link: centre of mass and principal moments, geometry.
fn physical_lines(link: &urdf_rs::Link) -> Vec<String> {
    let mut lines = Vec::new();
    if has_inertial(link) {
        let com = link.inertial.origin.xyz;
        let [a, b, c] = principal_moments(&link.inertial.inertia).map(num);
        lines.push(format!(
            "inertial: centre of mass ({}, {}, {}) m, principal moments {a}, {b}, {c} kg·m²",
            num(com[0]),
            num(com[1]),
            num(com[2])
        ));
    }
    for (kind, geometries) in [
        (
            "collision",
            link.collision
                .iter()
                .map(|c| &c.geometry)
                .collect::<Vec<_>>(),
        ),
        ("visual", link.visual.iter().map(|v| &v.geometry).collect()),
    ] {
        if !geometries.is_empty() {
            let shapes: Vec<_> = geometries.into_iter().map(describe_geometry).collect();
            lines.push(format!("{kind}: {}", shapes.join("; ")));
        }
    }
    lines
}

fn describe_geometry(geometry: &urdf_rs::Geometry) -> String {
    match geometry {
        urdf_rs::Geometry::Box { size } => {
            format!(
                "box {} × {} × {} m",
                num(size[0]),
                num(size[1]),
                num(size[2])
            )
        }
        urdf_rs::Geometry::Sphere { radius } => format!("sphere radius {} m", num(*radius)),
        urdf_rs::Geometry::Cylinder { radius, length } => format!(
            "cylinder radius {} m, length {} m",
            num(*radius),
            num(*length)
        ),
        urdf_rs::Geometry::Capsule { radius, length } => format!(
            "capsule radius {} m, length {} m",
            num(*radius),
            num(*length)
        ),
        urdf_rs::Geometry::Mesh { filename, scale } => match scale {
            Some(s) => format!(
                "mesh {filename} scaled ({}, {}, {})",
                num(s[0]),
                num(s[1]),
                num(s[2])
            ),
            None => format!("mesh {filename}"),
        },
    }
}

/// A number to four significant digits, without trailing zeros.
fn num(value: f64) -> String {
    if value == 0.0 {
        return "0".to_owned();
    }
    if !value.is_finite() {
        return format!("{value}");
    }
    let decimals = (3 - value.abs().log10().floor() as i64).clamp(0, 15) as usize;
    let text = format!("{value:.decimals$}");
    if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.').to_owned()
    } else {
        text
    }
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
    // Infinite: the URDF gives none (a continuous joint without `<limit>`).
    let given = |value: f64, unit: &str| {
        if value.is_finite() {
            format!("{value} {unit}")
        } else {
            "not given".to_owned()
        }
    };
    format!(
        "{}: {}, axis ({}, {}, {}), {range}, effort {}, velocity {}",
        joint.name,
        joint.type_name(),
        axis.x,
        axis.y,
        axis.z,
        given(limits.effort, effort),
        given(limits.velocity, velocity)
    )
}

fn fk(file: &Path, base: &str, tip: &str, q: &str, json: bool) -> Result<()> {
    let (_, tree) = load(file)?;
    let chain = tree
        .chain(base, tip)
        .with_context(|| format!("in URDF {}", file.display()))?;
    let q = parse_joint_values(q)?;
    // A configuration the joints cannot reach has no pose worth printing.
    for ((i, (name, limits)), &value) in chain.joint_names().zip(chain.limits()).enumerate().zip(&q)
    {
        if !(limits.lower..=limits.upper).contains(&value) {
            bail!(
                "--q entry {} ({value}) is outside joint \"{name}\"'s URDF limits [{}, {}]",
                i + 1,
                limits.lower,
                limits.upper
            );
        }
    }
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
        outln!(
            r#"{{"translation":{},"rotation_xyzw":{}}}"#,
            serde_json::to_string(&translation)?,
            serde_json::to_string(&rotation_xyzw)?
        )?;
    } else {
        let (roll, pitch, yaw) = pose.rotation.euler_angles();
        outln!(
            "pose of {tip} in the {base} frame:\n  translation (m):     {}\n  \
             quaternion (xyzw):   {}\n  rpy (rad):           {}",
            fmt_values(&translation),
            fmt_values(&rotation_xyzw),
            fmt_values(&[roll, pitch, yaw])
        )?;
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
