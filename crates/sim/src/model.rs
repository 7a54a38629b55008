//! Rigid-body models read from URDF: the bodies a rapier multibody needs.
//!
//! Links joined by fixed joints move as one rigid body in the simulator, so they are merged:
//! every movable joint's child (and the root) starts a body, and fixed-joint descendants add
//! their inertia and colliders to it at their offset. Each body's frame is its first link's
//! URDF frame, so a body's pose is directly comparable with core's forward kinematics.
//! Structure and limits come from core's validated [`KinematicTree`]; inertias, collision
//! shapes and joint damping, which core does not keep, from the same parsed URDF.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use moonhaul_core::kinematics::{urdf_pose, JointLimits, KinematicTree, MotionKind};
use nalgebra::{Isometry3, Matrix3, Unit, Vector3};

use crate::SimError;

/// Mass, centre of mass and inertia about it, in a body frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Inertia {
    pub mass_kg: f64,
    pub com_m: Vector3<f64>,
    pub inertia_kgm2: Matrix3<f64>,
}

impl Inertia {
    const ZERO: Inertia = Inertia {
        mass_kg: 0.0,
        com_m: Vector3::new(0.0, 0.0, 0.0),
        inertia_kgm2: Matrix3::new(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    };

    /// This inertia expressed in a frame where its own frame sits at `offset`.
    fn transformed(&self, offset: &Isometry3<f64>) -> Inertia {
        let r = offset.rotation.to_rotation_matrix();
        Inertia {
            mass_kg: self.mass_kg,
            com_m: offset.transform_point(&self.com_m.into()).coords,
            inertia_kgm2: r.matrix() * self.inertia_kgm2 * r.matrix().transpose(),
        }
    }

    /// The combined inertia of two parts (parallel-axis theorem).
    fn add(&self, other: &Inertia) -> Inertia {
        let mass_kg = self.mass_kg + other.mass_kg;
        if mass_kg <= 0.0 {
            return Inertia::ZERO;
        }
        let com_m = (self.com_m * self.mass_kg + other.com_m * other.mass_kg) / mass_kg;
        let shifted = |part: &Inertia| {
            let d = part.com_m - com_m;
            part.inertia_kgm2
                + (Matrix3::identity() * d.norm_squared() - d * d.transpose()) * part.mass_kg
        };
        Inertia {
            mass_kg,
            com_m,
            inertia_kgm2: shifted(self) + shifted(other),
        }
    }
}

/// A collision shape in a body frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    Ball { radius_m: f64 },
    Cuboid { half_extents_m: Vector3<f64> },
}

/// A collider of a body.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColliderSpec {
    pub pose: Isometry3<f64>,
    pub shape: Shape,
}

/// The one-DOF revolute joint that attaches a body to its parent body.
#[derive(Debug, Clone, PartialEq)]
pub struct BodyJoint {
    pub name: String,
    pub parent: usize,
    /// The joint frame in the parent body's frame.
    pub frame_in_parent: Isometry3<f64>,
    /// Unit rotation axis in the joint frame.
    pub axis: Unit<Vector3<f64>>,
    /// Position limits are infinite for continuous joints.
    pub limits: JointLimits,
    /// Viscous damping from `<dynamics damping>`, N·m·s/rad.
    pub damping: f64,
}

/// One rigid body of a model.
#[derive(Debug, Clone, PartialEq)]
pub struct Body {
    /// The URDF link whose frame is this body's frame.
    pub link: String,
    pub joint: Option<BodyJoint>,
    pub inertia: Inertia,
    pub colliders: Vec<ColliderSpec>,
}

/// A URDF model split into rigid bodies; `bodies[0]` is the root, parents precede children.
#[derive(Debug, Clone)]
pub struct RobotModel {
    pub path: PathBuf,
    pub tree: KinematicTree,
    pub bodies: Vec<Body>,
    /// Per link name: its body and its frame in that body's frame.
    link_frames: HashMap<String, (usize, Isometry3<f64>)>,
}

/// Reads a URDF with core's size-capped, XML-shape-checked reader; the error names the file
/// once (`SimError::Model` carries the path).
pub fn read_urdf(path: &Path) -> Result<urdf_rs::Robot, SimError> {
    moonhaul_core::kinematics::read_urdf(path).map_err(|e| SimError::Model {
        path: path.to_owned(),
        reason: e.without_file().to_string(),
    })
}

impl RobotModel {
    /// Reads a URDF; errors name the file and the link or joint at fault.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self, SimError> {
        let path = path.as_ref();
        Self::from_robot(path, &read_urdf(path)?)
    }

    /// Splits an already parsed URDF (read from `path`, which errors name) into bodies.
    pub fn from_robot(path: &Path, robot: &urdf_rs::Robot) -> Result<Self, SimError> {
        let path = path.to_owned();
        let tree = KinematicTree::from_robot(robot).map_err(|e| SimError::Model {
            path: path.clone(),
            reason: e.to_string(),
        })?;
        let fail = |reason: String| SimError::Model {
            path: path.clone(),
            reason,
        };
        let urdf_links: HashMap<&str, &urdf_rs::Link> =
            robot.links.iter().map(|l| (l.name.as_str(), l)).collect();
        let damping: HashMap<&str, f64> = robot
            .joints
            .iter()
            .map(|j| {
                (
                    j.name.as_str(),
                    j.dynamics.as_ref().map_or(0.0, |d| d.damping),
                )
            })
            .collect();

        let mut model = RobotModel {
            path: path.clone(),
            tree: tree.clone(),
            bodies: Vec::new(),
            link_frames: HashMap::new(),
        };
        // Depth-first from the root: (link, its body, its frame in that body).
        let mut stack = vec![(
            tree.root().name.clone(),
            None::<BodyJoint>,
            None::<(usize, Isometry3<f64>)>,
        )];
        while let Some((link, joint, merged_into)) = stack.pop() {
            let (body, offset) = match merged_into {
                Some(at) => at,
                None => {
                    model.bodies.push(Body {
                        link: link.clone(),
                        joint,
                        inertia: Inertia::ZERO,
                        colliders: Vec::new(),
                    });
                    (model.bodies.len() - 1, Isometry3::identity())
                }
            };
            let urdf_link = urdf_links
                .get(link.as_str())
                .ok_or_else(|| fail(format!("link {link:?} missing")))?;
            model.link_frames.insert(link.clone(), (body, offset));
            let inertial = &urdf_link.inertial;
            if inertial.mass.value > 0.0 {
                let i = &inertial.inertia;
                let local = Inertia {
                    mass_kg: inertial.mass.value,
                    com_m: Vector3::zeros(),
                    inertia_kgm2: Matrix3::new(
                        i.ixx, i.ixy, i.ixz, i.ixy, i.iyy, i.iyz, i.ixz, i.iyz, i.izz,
                    ),
                };
                let placed = local.transformed(&(offset * urdf_pose(&inertial.origin)));
                let b = &mut model.bodies[body];
                b.inertia = b.inertia.add(&placed);
            }
            for collision in &urdf_link.collision {
                let shape = match &collision.geometry {
                    urdf_rs::Geometry::Sphere { radius } => Shape::Ball { radius_m: *radius },
                    urdf_rs::Geometry::Box { size } => {
                        Shape::Cuboid { half_extents_m: Vector3::from(size.0) / 2.0 }
                    }
                    other => {
                        return Err(fail(format!(
                            "link {link:?}: collision geometry {other:?} is not supported (use sphere or box)"
                        )))
                    }
                };
                let pose = offset * urdf_pose(&collision.origin);
                model.bodies[body]
                    .colliders
                    .push(ColliderSpec { pose, shape });
            }
            for (j, child) in tree.children(&link).map_err(|e| fail(e.to_string()))? {
                let frame = offset * j.origin;
                match &j.motion {
                    None => stack.push((child.name.clone(), None, Some((body, frame)))),
                    Some(m) if m.kind == MotionKind::Prismatic => {
                        return Err(fail(format!(
                            "joint {:?}: prismatic joints are not simulated",
                            j.name
                        )))
                    }
                    Some(m) => stack.push((
                        child.name.clone(),
                        Some(BodyJoint {
                            name: j.name.clone(),
                            parent: body,
                            frame_in_parent: frame,
                            axis: m.axis,
                            limits: m.limits,
                            damping: damping.get(j.name.as_str()).copied().unwrap_or(0.0),
                        }),
                        None,
                    )),
                }
            }
        }
        if let Some(b) = model.bodies.iter().find(|b| b.inertia.mass_kg <= 0.0) {
            return Err(fail(format!("body of link {:?} has no mass", b.link)));
        }
        Ok(model)
    }

    /// The body a link belongs to and the link's frame in that body's frame.
    pub fn link_frame(&self, link: &str) -> Result<(usize, Isometry3<f64>), SimError> {
        self.link_frames
            .get(link)
            .copied()
            .ok_or_else(|| SimError::Model {
                path: self.path.clone(),
                reason: format!("no link {link:?}"),
            })
    }

    /// The body that a movable joint moves.
    pub fn joint_body(&self, joint: &str) -> Result<usize, SimError> {
        self.bodies
            .iter()
            .position(|b| b.joint.as_ref().is_some_and(|j| j.name == joint))
            .ok_or_else(|| SimError::Model {
                path: self.path.clone(),
                reason: format!("no movable joint {joint:?}"),
            })
    }

    /// Total mass, kg.
    pub fn mass_kg(&self) -> f64 {
        self.bodies.iter().map(|b| b.inertia.mass_kg).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) fn asset(name: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../assets")
            .join(name)
    }

    #[test]
    fn the_unit_splits_into_root_two_wheels_and_seven_arm_links() {
        let unit = RobotModel::from_file(asset("unit.urdf")).unwrap();
        assert_eq!(unit.bodies.len(), 10);
        assert!((unit.mass_kg() - unit.tree.total_mass()).abs() < 1e-9);
        // Casters and the arm base merge into the base body.
        assert_eq!(unit.link_frame("caster_front").unwrap().0, 0);
        assert_eq!(unit.link_frame("arm_link_0").unwrap().0, 0);
        // The end effector merges into link 7 at the flange + paddle offset.
        let (body, frame) = unit.link_frame("ee").unwrap();
        assert_eq!(unit.bodies[body].link, "arm_link_7");
        assert!((frame.translation.vector.z - 0.145).abs() < 1e-12);
        let base = &unit.bodies[0];
        assert_eq!(base.colliders.len(), 2);
        assert!(unit.joint_body("arm_joint_7").is_ok());
        assert!(unit.joint_body("arm_mount").is_err());
    }

    #[test]
    fn merged_inertia_obeys_the_parallel_axis_theorem() {
        let point = |m: f64, x: f64| Inertia {
            mass_kg: m,
            com_m: Vector3::new(x, 0.0, 0.0),
            inertia_kgm2: Matrix3::zeros(),
        };
        let both = point(1.0, -1.0).add(&point(1.0, 1.0));
        assert_eq!(both.com_m, Vector3::zeros());
        assert!((both.inertia_kgm2[(1, 1)] - 2.0).abs() < 1e-12);
        assert!(both.inertia_kgm2[(0, 0)].abs() < 1e-12);
    }

    #[test]
    fn payloads_have_the_papers_masses() {
        for (name, kg) in [("box", 7.5), ("bricks", 9.5), ("sledge", 5.3)] {
            let p = RobotModel::from_file(asset(&format!("payload_{name}.urdf"))).unwrap();
            assert_eq!(p.bodies.len(), 1);
            assert!((p.mass_kg() - kg).abs() < 1e-9);
            assert!(matches!(
                p.bodies[0].colliders[0].shape,
                Shape::Cuboid { .. }
            ));
        }
    }

    #[test]
    fn a_missing_file_is_named() {
        let err = RobotModel::from_file("nowhere.urdf").unwrap_err();
        assert!(err.to_string().contains("nowhere.urdf"));
    }
}
