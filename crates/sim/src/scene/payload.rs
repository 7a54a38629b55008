//! Payload URDFs: loading, the payload convention (see the [`super`] module docs), and the
//! custom payload slot ([`PayloadKind::Custom`]).

use std::path::{Path, PathBuf};

use moonhaul_core::kinematics::parse_urdf;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use nalgebra::Vector3;

use super::{PayloadModel, SceneModel};
use crate::model::{self, RobotModel};
use crate::randomization::PayloadKind;
use crate::SimError;

/// The one link a payload URDF has.
pub const PAYLOAD_LINK: &str = "payload";

/// Checks `robot` (read from `path`) against the payload convention and returns its box's half
/// extents, m. Core's reader has already checked the physical values (finite, non-negative
/// mass, plausible inertia, positive box sizes); this checks what the scene relies on.
fn check_convention(path: &Path, robot: &urdf_rs::Robot) -> Result<Vector3<f64>, SimError> {
    let fail = |reason: String| SimError::Model {
        path: path.to_owned(),
        reason,
    };
    let link = match robot.links.as_slice() {
        [link] => link,
        links => {
            let names: Vec<&str> = links.iter().map(|l| l.name.as_str()).collect();
            return Err(fail(format!(
                "a payload has exactly one link, named {PAYLOAD_LINK:?}; found {} ({names:?})",
                links.len()
            )));
        }
    };
    if link.name != PAYLOAD_LINK {
        return Err(fail(format!(
            "the payload's link is named {:?}, not {PAYLOAD_LINK:?}",
            link.name
        )));
    }
    let mass = link.inertial.mass.value;
    if mass <= 0.0 {
        return Err(fail(format!(
            "link {PAYLOAD_LINK:?}: mass {mass} kg; a payload needs an <inertial> with a \
             positive mass"
        )));
    }
    let collision = match link.collision.as_slice() {
        [c] => c,
        cs => {
            return Err(fail(format!(
                "link {PAYLOAD_LINK:?} has {} <collision> elements; a payload has exactly one, \
                 a <box>",
                cs.len()
            )))
        }
    };
    let size = match &collision.geometry {
        urdf_rs::Geometry::Box { size } => size.0,
        other => {
            return Err(fail(format!(
                "link {PAYLOAD_LINK:?}: collision geometry {other:?} is not a <box>; the grasp \
                 and the scene need the payload's box"
            )))
        }
    };
    // The scene places the box at the link frame, axis-aligned; an offset box would be
    // grasped and collided in the wrong place.
    let origin = &collision.origin;
    if origin.xyz.0 != [0.0; 3] || origin.rpy.0 != [0.0; 3] {
        return Err(fail(format!(
            "link {PAYLOAD_LINK:?}: the <collision> origin must be zero (the box centred on and \
             aligned with the link frame), got xyz {:?}, rpy {:?}",
            origin.xyz.0, origin.rpy.0
        )));
    }
    // The units grasp the long sides and travel along x.
    if size[0] < size[1] {
        return Err(fail(format!(
            "box size {} × {} × {} m: the long side must lie along x (size x ≥ size y), the \
             direction of travel",
            size[0], size[1], size[2]
        )));
    }
    Ok(Vector3::from(size) / 2.0)
}

impl SceneModel {
    /// Loads the payload URDF at `path`, checks the payload convention and solves its grasp.
    pub(super) fn load_payload(&self, path: &Path) -> Result<PayloadModel, SimError> {
        self.payload_model(path, &model::read_urdf(path)?)
    }

    /// Checks a parsed payload URDF (`path` names it in errors) and solves its grasp.
    fn payload_model(&self, path: &Path, robot: &urdf_rs::Robot) -> Result<PayloadModel, SimError> {
        let half_extents_m = check_convention(path, robot)?;
        let model = RobotModel::from_robot(path, robot)?;
        let lift_path_q_rad = self
            .solve_grasp(&half_extents_m)
            .map_err(|e| SimError::Model {
                path: path.to_owned(),
                reason: format!("not graspable: {e}"),
            })?;
        Ok(PayloadModel {
            model,
            half_extents_m,
            grasp_q_rad: lift_path_q_rad[0],
            lift_path_q_rad,
        })
    }

    /// Generates the family of `[randomization.generated_payloads]` as
    /// [`PayloadKind::Generated`] members, each built from its URDF text through the checks a
    /// payload file passes. A draw whose grasp the arm cannot reach is drawn again (the next
    /// draw from the family's stream), a few times at most.
    pub(super) fn generate_payloads(&mut self) -> Result<(), SimError> {
        const ATTEMPTS: usize = 8;
        let family = self.config.randomization.generated_payloads.clone();
        let mut rng = ChaCha8Rng::seed_from_u64(family.seed);
        for i in 0..family.count {
            let kind = PayloadKind::Generated(i);
            let name = self.payload_name(kind);
            let path = PathBuf::from(format!("[randomization.generated_payloads] member {name}"));
            let mut attempt = || {
                let text = family.draw(&mut rng).urdf(&name);
                let robot = parse_urdf(&text).map_err(|e| SimError::Model {
                    path: path.clone(),
                    reason: e.to_string(),
                })?;
                self.payload_model(&path, &robot)
            };
            let mut result = attempt();
            for _ in 1..ATTEMPTS {
                if result.is_ok() {
                    break;
                }
                result = attempt();
            }
            let payload = result.map_err(|e| SimError::Config {
                field: "randomization.generated_payloads",
                reason: format!("{ATTEMPTS} draws of {name} in a row were not graspable: {e}"),
            })?;
            self.payloads.insert(kind, payload);
        }
        Ok(())
    }

    /// Loads the payload URDF at `path` (see the [`super`] module docs for what it must be),
    /// checks it and solves its grasp, and stores it as [`PayloadKind::Custom`], replacing any
    /// earlier one (a scene holds one custom payload). On error the scene is unchanged.
    pub fn add_payload_file(&mut self, path: &Path) -> Result<PayloadKind, SimError> {
        let payload = self.load_payload(path)?;
        self.payloads.insert(PayloadKind::Custom, payload);
        Ok(PayloadKind::Custom)
    }

    /// The model of `kind`; an error for [`PayloadKind::Custom`] before a file was added.
    pub fn payload(&self, kind: PayloadKind) -> Result<&PayloadModel, SimError> {
        self.payloads.get(&kind).ok_or_else(|| SimError::Config {
            field: "payload",
            reason: format!(
                "no {} payload in this scene (a custom payload needs \
                 SceneModel::add_payload_file first)",
                kind.name()
            ),
        })
    }

    /// The payload's name for output folders and reports: `box`, `bricks`, `sledge`, `gen<i>`
    /// for a generated one, or the custom payload's file stem (`crate_small` for
    /// `crate_small.urdf`).
    pub fn payload_name(&self, kind: PayloadKind) -> String {
        match (kind, self.payloads.get(&kind)) {
            (PayloadKind::Custom, Some(p)) => p
                .model
                .path
                .file_stem()
                .map_or_else(|| kind.label(), |s| s.to_string_lossy().into_owned()),
            _ => kind.label(),
        }
    }
}
