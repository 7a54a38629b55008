//! Physical plausibility of a URDF link: its inertial and its collision and visual geometry.
//! (Joint limits and dynamics are checked with the joint, in [`super::Motion`].)
//!
//! - Inertial: a link without `<inertial>` is a massless frame link (an `ee` frame, say).
//!   urdf_rs reads an absent `<inertial>` as mass 0 with zero inertia, exactly what an explicit
//!   `<mass value="0"/>` with zero inertia reads as, so the two cannot be told apart and both
//!   mean "no inertial". Any other inertial needs a finite mass > 0 (a zero mass with a
//!   non-zero inertia is a contradiction, not a frame link). Beyond that the
//!   inertial origin finite, and the inertia finite, positive semi-definite and with principal
//!   moments that obey the triangle inequality (each at most the sum of the other two), as
//!   every rigid body's do. URDF gives the inertia as its six upper-triangle entries, so the
//!   matrix is symmetric by construction.
//! - Geometry: box sizes, sphere radii and cylinder and capsule radii and lengths finite and
//!   positive; mesh scales finite and non-zero (negative mirrors); origins finite.

use nalgebra::Matrix3;

use super::KinematicsError;

/// Relative tolerance of the inertia checks: an eigenvalue may be as low as −tol·|λ|max and the
/// largest principal moment exceed the sum of the other two by tol·λmax. URDF exporters print
/// about six significant digits, so a thin rod or a flat plate, which meets the triangle
/// inequality with equality, can miss it by a few parts in 10⁶ after rounding.
pub const INERTIA_REL_TOL: f64 = 1e-5;

/// The six URDF inertia entries with their attribute names.
fn entries(i: &urdf_rs::Inertia) -> [(&'static str, f64); 6] {
    [
        ("ixx", i.ixx),
        ("ixy", i.ixy),
        ("ixz", i.ixz),
        ("iyy", i.iyy),
        ("iyz", i.iyz),
        ("izz", i.izz),
    ]
}

/// The principal moments of inertia (kg·m²), ascending: the eigenvalues of the symmetric
/// inertia matrix the six URDF entries describe. NaN if an entry is not finite.
pub fn principal_moments(inertia: &urdf_rs::Inertia) -> [f64; 3] {
    let values = entries(inertia).map(|(_, v)| v);
    let [ixx, ixy, ixz, iyy, iyz, izz] = values;
    if !values.iter().all(|v| v.is_finite()) {
        return [f64::NAN; 3];
    }
    // Scale to unit size first, so that entries near f64::MAX do not overflow the solver.
    let scale = values.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
    if scale == 0.0 {
        return [0.0; 3];
    }
    let s = |v: f64| v / scale;
    let matrix = Matrix3::new(
        s(ixx),
        s(ixy),
        s(ixz),
        s(ixy),
        s(iyy),
        s(iyz),
        s(ixz),
        s(iyz),
        s(izz),
    );
    let mut moments: [f64; 3] = matrix.symmetric_eigenvalues().into();
    moments.sort_by(f64::total_cmp);
    moments.map(|m| m * scale)
}

/// A moment of inertia to seven significant digits, enough to show a violation of the
/// [`INERTIA_REL_TOL`] tolerance, without trailing zeros.
fn moment(value: f64) -> String {
    if value == 0.0 || !value.is_finite() {
        return format!("{value}");
    }
    let decimals = (6 - value.abs().log10().floor() as i64).clamp(0, 20) as usize;
    let text = format!("{value:.decimals$}");
    if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.').to_owned()
    } else {
        text
    }
}

/// Largest distance or size anywhere in a robot model, m: a model a kilometre across is a unit
/// error (millimetres for metres), not a robot.
pub const MAX_EXTENT_M: f64 = 1000.0;
/// Largest mass of one link, kg.
pub const MAX_LINK_MASS_KG: f64 = 1e5;

/// Finite, with its translation within [`MAX_EXTENT_M`].
pub(super) fn pose_is_finite(pose: &urdf_rs::Pose) -> bool {
    pose.xyz
        .iter()
        .all(|v| v.is_finite() && v.abs() <= MAX_EXTENT_M)
        && pose.rpy.iter().all(|v| v.is_finite())
}

fn fmt_pose(pose: &urdf_rs::Pose) -> String {
    format!("xyz {:?}, rpy {:?}", pose.xyz.0, pose.rpy.0)
}

/// Checks a link's inertial and geometry (see the module docs).
pub(super) fn check_link(link: &urdf_rs::Link) -> Result<(), KinematicsError> {
    check_inertial(link)?;
    for (i, visual) in link.visual.iter().enumerate() {
        check_geometry(
            link,
            "visual",
            i,
            visual.name.as_deref(),
            &visual.origin,
            &visual.geometry,
        )?;
    }
    for (i, collision) in link.collision.iter().enumerate() {
        check_geometry(
            link,
            "collision",
            i,
            collision.name.as_deref(),
            &collision.origin,
            &collision.geometry,
        )?;
    }
    Ok(())
}

fn check_inertial(link: &urdf_rs::Link) -> Result<(), KinematicsError> {
    let bad = |reason: String| KinematicsError::BadInertial {
        link: link.name.clone(),
        reason,
    };
    let urdf_rs::Inertial {
        origin,
        mass,
        inertia,
    } = &link.inertial;
    if !pose_is_finite(origin) {
        return Err(bad(format!(
            "origin is not finite or beyond {MAX_EXTENT_M} m ({})",
            fmt_pose(origin)
        )));
    }
    let mass = mass.value;
    if !mass.is_finite() {
        return Err(bad(format!("mass is {mass}, not a finite number of kg")));
    }
    if mass < 0.0 {
        return Err(bad(format!("mass {mass} kg is negative")));
    }
    if mass > MAX_LINK_MASS_KG {
        return Err(bad(format!(
            "mass {mass:?} kg exceeds {MAX_LINK_MASS_KG:?} kg for one link"
        )));
    }
    for (name, value) in entries(inertia) {
        if !value.is_finite() {
            return Err(bad(format!("inertia {name} is {value}, not finite")));
        }
    }
    let no_inertia = entries(inertia).iter().all(|&(_, v)| v == 0.0);
    if mass == 0.0 && !no_inertia {
        return Err(bad(
            "mass is 0 kg but the inertia is not zero: a mass must be positive (a frame link \
             has no <inertial>)"
                .into(),
        ));
    }
    let [low, mid, high] = principal_moments(inertia);
    let tol = INERTIA_REL_TOL * low.abs().max(high.abs());
    let [l, m, h] = [low, mid, high].map(moment);
    if low < -tol {
        return Err(bad(format!(
            "inertia is not positive semi-definite (eigenvalues {l}, {m}, {h} kg·m²)"
        )));
    }
    if high > low + mid + tol {
        return Err(bad(format!(
            "inertia violates the triangle inequality: principal moment {h} kg·m² exceeds the \
             sum of the other two, {l} + {m}"
        )));
    }
    Ok(())
}

fn check_geometry(
    link: &urdf_rs::Link,
    kind: &str,
    index: usize,
    name: Option<&str>,
    origin: &urdf_rs::Pose,
    geometry: &urdf_rs::Geometry,
) -> Result<(), KinematicsError> {
    let bad = |reason: String| KinematicsError::BadGeometry {
        link: link.name.clone(),
        element: match name {
            Some(name) => format!("{kind} \"{name}\""),
            None => format!("{kind} #{}", index + 1),
        },
        reason,
    };
    if !pose_is_finite(origin) {
        return Err(bad(format!(
            "origin is not finite or beyond {MAX_EXTENT_M} m ({})",
            fmt_pose(origin)
        )));
    }
    let positive = |v: &f64| v.is_finite() && *v > 0.0 && *v <= MAX_EXTENT_M;
    match geometry {
        urdf_rs::Geometry::Box { size } if !size.iter().all(positive) => Err(bad(format!(
            "box size {:?} m must be finite, > 0 and at most {MAX_EXTENT_M} m",
            size.0
        ))),
        urdf_rs::Geometry::Sphere { radius } if !positive(radius) => Err(bad(format!(
            "sphere radius {radius} m must be finite, > 0 and at most {MAX_EXTENT_M} m"
        ))),
        urdf_rs::Geometry::Cylinder { radius, length }
        | urdf_rs::Geometry::Capsule { radius, length }
            if !(positive(radius) && positive(length)) =>
        {
            let shape = match geometry {
                urdf_rs::Geometry::Cylinder { .. } => "cylinder",
                _ => "capsule",
            };
            Err(bad(format!(
                "{shape} radius {radius} m and length {length} m must be finite, > 0 and at most {MAX_EXTENT_M} m"
            )))
        }
        urdf_rs::Geometry::Mesh {
            scale: Some(scale), ..
        } if !scale.iter().all(|v| v.is_finite() && *v != 0.0) => Err(bad(format!(
            "mesh scale {:?} must be finite and non-zero",
            scale.0
        ))),
        _ => Ok(()),
    }
}
