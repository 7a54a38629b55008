//! URDF kinematic trees and forward kinematics between any two links.
//!
//! Conventions are URDF's:
//! - Every link has a frame. A joint's `origin` places the joint frame in its parent link's frame;
//!   at joint value q the child link frame is `parent · origin · motion(q)`, where `motion` rotates
//!   by q rad about the joint's axis (revolute, continuous) or translates by q m along it
//!   (prismatic). The axis is expressed in the joint frame, defaults to +x and is normalized here.
//! - `origin rpy` are fixed-axis roll, pitch, yaw: R = Rz(yaw)·Ry(pitch)·Rx(roll).
//! - [`Chain::forward`] returns T_base_tip, the tip link frame expressed in the base link frame
//!   (p_base = T · p_tip).
//! - A [`Chain`] runs from `base` up to the deepest common ancestor, then down to `tip`. Joints on
//!   the upward part are traversed *inversely*: they contribute `(origin · motion(q))⁻¹`, with q
//!   still the joint's own URDF position. Joint values are ordered as the movable joints are
//!   traversed from base to tip ([`Chain::joint_names`]), so `chain(tip, base)` takes them in
//!   reverse order and yields the inverse pose.
//!
//! Reading is bounded and validation physical, so every loader of a URDF ([`read_urdf`],
//! [`KinematicTree::from_file`], [`KinematicTree::from_robot`]) gets the same checks:
//! - the file is read through [`crate::input::read_capped_text`] (at most
//!   [`crate::input::MAX_URDF_BYTES`]), and its XML is scanned, before it is parsed, for at most
//!   [`MAX_XML_DEPTH`] levels of element nesting and [`MAX_XML_ELEMENTS`] elements (the XML
//!   parser and urdf_rs recurse once per level);
//! - a tree has at most [`MAX_LINKS`] links and [`MAX_JOINTS`] joints, and nothing here
//!   recurses along the kinematic tree, so a chain of that many links is fine;
//! - movable joints have positive effort and velocity limits where the URDF gives them (a
//!   continuous joint may omit `<limit>`: then they are unknown, which kinematics never needs),
//!   finite position limits (revolute, prismatic: their `<limit>` is required) and finite,
//!   non-negative `<dynamics>`; links have plausible inertials and geometry (see [`physical`]
//!   for exactly what is checked and why mass 0 is allowed).

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};
use thiserror::Error;

use crate::input::{read_capped_text, InputError, MAX_URDF_BYTES};

pub mod physical;
pub use physical::principal_moments;
/// The urdf_rs whose types [`read_urdf`] returns and [`KinematicTree::from_robot`] takes, so
/// callers name the same version.
pub use urdf_rs;

/// Deepest element nesting accepted in URDF XML. Real URDFs nest 5 deep
/// (`robot/link/visual/geometry/mesh`); the XML parser recurses once per level.
pub const MAX_XML_DEPTH: usize = 64;
/// Most XML elements accepted in one URDF: room for [`MAX_LINKS`] links of about 20 elements
/// each (inertial, visual and collision with origins, and the joint to each link), while
/// bounding the memory the parsed document takes.
pub const MAX_XML_ELEMENTS: usize = 200_000;
/// Most links accepted in one URDF (a unit has 18; a 10,000-link chain still loads quickly).
pub const MAX_LINKS: usize = 10_000;
/// Most joints accepted in one URDF (a tree of [`MAX_LINKS`] links has one fewer).
pub const MAX_JOINTS: usize = 10_000;

/// Why a URDF cannot be used, or a chain cannot be built or evaluated. Each variant names the
/// offending element.
#[derive(Debug, Error)]
pub enum KinematicsError {
    /// The URDF file cannot be read: missing, not a regular file, too large, not UTF-8.
    #[error(transparent)]
    Input(#[from] InputError),
    /// Any other error, in the URDF file at `path` ([`read_urdf`], [`KinematicTree::from_file`]).
    #[error("URDF {}: {error}", path.display())]
    File {
        path: PathBuf,
        error: Box<KinematicsError>,
    },
    #[error("cannot parse URDF XML: {0}")]
    Parse(urdf_rs::UrdfError),
    #[error("URDF XML nests elements more than {max} deep (line {line})")]
    XmlTooDeep { max: usize, line: usize },
    #[error("URDF XML has more than {max} elements (line {line})")]
    XmlTooManyElements { max: usize, line: usize },
    #[error("URDF has {count} {what}, more than the {max} supported")]
    TooMany {
        what: &'static str,
        count: usize,
        max: usize,
    },
    #[error("URDF has no links")]
    NoLinks,
    #[error("a {element} has an empty name")]
    EmptyName { element: &'static str },
    #[error("link \"{link}\" is defined more than once")]
    DuplicateLink { link: String },
    #[error("joint \"{joint}\" is defined more than once")]
    DuplicateJoint { joint: String },
    #[error(
        "joint \"{joint}\" has unsupported type \"{kind}\" (supported: fixed, revolute, continuous, prismatic)"
    )]
    UnsupportedJointType { joint: String, kind: String },
    #[error("joint \"{joint}\" refers to missing link \"{link}\"")]
    MissingLink { joint: String, link: String },
    #[error("link \"{link}\" is the child of two joints, \"{first}\" and \"{second}\"")]
    TwoParents {
        link: String,
        first: String,
        second: String,
    },
    #[error("link \"{link}\" is on a cycle of joints")]
    Cycle { link: String },
    #[error("URDF has more than one root link: \"{first}\" and \"{second}\"")]
    MultipleRoots { first: String, second: String },
    #[error(
        "joint \"{joint}\" has a non-finite origin or one beyond {} m",
        physical::MAX_EXTENT_M
    )]
    NonFiniteOrigin { joint: String },
    #[error("joint \"{joint}\" has a zero or non-finite axis {axis:?}")]
    BadAxis { joint: String, axis: [f64; 3] },
    /// A revolute or prismatic joint without `<limit>`, which the URDF format requires for
    /// them (a continuous joint may omit it).
    #[error(
        "joint \"{joint}\" has no <limit>, which URDF requires of revolute and prismatic joints"
    )]
    MissingLimit { joint: String },
    #[error("joint \"{joint}\" has invalid position limits: lower {lower}, upper {upper}")]
    BadLimits {
        joint: String,
        lower: f64,
        upper: f64,
    },
    /// An `<inertial>` that no rigid body has (see [`physical`]).
    #[error("link \"{link}\": inertial {reason}")]
    BadInertial { link: String, reason: String },
    /// A `<limit>` or `<dynamics>` value of a movable joint out of range; `field` names the
    /// element and attribute, e.g. "limit effort".
    #[error("joint \"{joint}\": {field} is {value}, expected {expected}")]
    BadJointValue {
        joint: String,
        field: &'static str,
        value: f64,
        expected: &'static str,
    },
    /// A `<visual>` or `<collision>` with an impossible shape or a non-finite origin; `element`
    /// is e.g. `collision #2` (1-based, in URDF order) or `visual "name"`.
    #[error("link \"{link}\": {element}: {reason}")]
    BadGeometry {
        link: String,
        element: String,
        reason: String,
    },
    #[error("unknown link \"{link}\"")]
    UnknownLink { link: String },
    #[error("expected {expected} joint values, got {got}")]
    WrongJointCount { expected: usize, got: usize },
}

type Result<T, E = KinematicsError> = std::result::Result<T, E>;

impl KinematicsError {
    /// The error itself, without the [`KinematicsError::File`] that names its file.
    pub fn without_file(&self) -> &KinematicsError {
        match self {
            KinematicsError::File { error, .. } => error,
            other => other,
        }
    }

    fn in_file(self, path: &Path) -> Self {
        match self {
            // Already names its file.
            KinematicsError::Input(_) | KinematicsError::File { .. } => self,
            error => KinematicsError::File {
                path: path.to_owned(),
                error: Box::new(error),
            },
        }
    }
}

/// Reads a URDF file: size-capped ([`crate::input::MAX_URDF_BYTES`]), its XML shape-checked
/// ([`MAX_XML_DEPTH`], [`MAX_XML_ELEMENTS`]) before it is parsed, then parsed by urdf_rs. Not
/// yet validated: pass the result to [`KinematicTree::from_robot`] (which
/// [`KinematicTree::from_file`] does). Errors name the file.
pub fn read_urdf(path: &Path) -> Result<urdf_rs::Robot> {
    let text = read_capped_text(path, MAX_URDF_BYTES)?;
    parse_urdf(&text).map_err(|e| e.in_file(path))
}

/// Parses URDF XML text, with the XML caps of [`read_urdf`].
pub fn parse_urdf(urdf: &str) -> Result<urdf_rs::Robot> {
    check_xml_shape(urdf)?;
    urdf_rs::read_from_string(urdf).map_err(KinematicsError::Parse)
}

/// Where [`check_xml_shape`] is in the XML: the states of urdf_rs's XML parser (RustyXML 0.3),
/// whose reading of comments, CDATA, processing instructions, DOCTYPE and attribute values
/// this follows byte for byte, so it never sees fewer elements or less nesting than the parser
/// does (every delimiter is ASCII, so bytes and chars agree). urdf_rs re-serializes what
/// RustyXML built and deserializes that with serde-xml-rs, which sees the same tree. Tied to
/// that parser: the `too_deep_xml` tests pin its quirks, so an urdf-rs upgrade that changes
/// them fails there.
#[derive(Clone, Copy)]
enum XmlScan {
    Text,
    TagOpened,
    Pi { question: bool },
    TagName,
    CloseTagName,
    InTag,
    AttrName { space: bool },
    ExpectDelimiter,
    AttrValue(u8),
    ExpectClose,
    ExpectSpaceOrClose,
    Exclamation,
    CommentOpening,
    Comment { dashes: u8 },
    CommentEnd,
    CdataOpening(usize),
    Cdata { brackets: u8 },
    Doctype(usize),
}

/// Rejects XML nested deeper than [`MAX_XML_DEPTH`] or with more than [`MAX_XML_ELEMENTS`]
/// elements, in one linear pass and before anything recursive sees it. Stops at the first
/// construct the parser rejects (it will report it).
fn check_xml_shape(xml: &str) -> Result<()> {
    use XmlScan::*;
    let (mut depth, mut elements, mut line) = (0usize, 0usize, 1usize);
    let mut state = Text;
    for &c in xml.as_bytes() {
        if c == b'\n' {
            line += 1;
        }
        let space = matches!(c, b' ' | b'\t' | b'\r' | b'\n');
        let mut start = false;
        state = match (state, c) {
            (Text, b'<') => TagOpened,
            (Text, _) => Text,
            (TagOpened, b'?') => Pi { question: false },
            (TagOpened, b'!') => Exclamation,
            (TagOpened, b'/') => CloseTagName,
            // Any other character, even '>' or a space, starts the name.
            (TagOpened, _) => TagName,
            (Pi { question: true }, b'>') => Text,
            (Pi { question }, _) => Pi {
                question: question || c == b'?',
            },
            (TagName | InTag, b'/') => {
                start = true;
                ExpectClose
            }
            (TagName | InTag, b'>') => {
                start = true;
                Text
            }
            (TagName, _) if space => InTag,
            (TagName, _) => TagName,
            (CloseTagName, b'>') => {
                depth = depth.saturating_sub(1);
                Text
            }
            (CloseTagName, _) if space => {
                depth = depth.saturating_sub(1);
                ExpectSpaceOrClose
            }
            (CloseTagName, _) => CloseTagName,
            (InTag, _) if space => InTag,
            (InTag, _) => AttrName { space: false },
            (AttrName { .. }, b'=') => ExpectDelimiter,
            (AttrName { .. }, _) if space => AttrName { space: true },
            (AttrName { space: false }, _) => AttrName { space: false },
            (ExpectDelimiter, b'"' | b'\'') => AttrValue(c),
            (ExpectDelimiter, _) if space => ExpectDelimiter,
            (AttrValue(delim), _) if c == delim => InTag,
            (AttrValue(delim), _) => AttrValue(delim),
            (ExpectClose, b'>') => {
                depth = depth.saturating_sub(1);
                Text
            }
            (ExpectSpaceOrClose, b'>') => Text,
            (ExpectSpaceOrClose, _) if space => ExpectSpaceOrClose,
            (Exclamation, b'-') => CommentOpening,
            (Exclamation, b'[') => CdataOpening(0),
            (Exclamation, b'D') => Doctype(0),
            (CommentOpening, b'-') => Comment { dashes: 0 },
            (Comment { dashes: 1 }, b'-') => CommentEnd,
            (Comment { .. }, b'-') => Comment { dashes: 1 },
            (Comment { .. }, _) => Comment { dashes: 0 },
            (CommentEnd, b'>') => Text,
            (CdataOpening(5), b'[') => Cdata { brackets: 0 },
            (CdataOpening(i), _) if i < 5 && c == b"CDATA"[i] => CdataOpening(i + 1),
            (Cdata { brackets }, b']') => Cdata {
                brackets: brackets.saturating_add(1),
            },
            (Cdata { brackets }, b'>') if brackets >= 2 => Text,
            (Cdata { .. }, _) => Cdata { brackets: 0 },
            (Doctype(i), _) if i < 6 && c == b"OCTYPE"[i] => Doctype(i + 1),
            (Doctype(6), _) if space => Doctype(7),
            (Doctype(7), b'>') => Text,
            (Doctype(7), _) => Doctype(7),
            // Everything else is a syntax error the parser reports.
            _ => return Ok(()),
        };
        if start {
            elements += 1;
            depth += 1;
            if depth > MAX_XML_DEPTH {
                return Err(KinematicsError::XmlTooDeep {
                    max: MAX_XML_DEPTH,
                    line,
                });
            }
            if elements > MAX_XML_ELEMENTS {
                return Err(KinematicsError::XmlTooManyElements {
                    max: MAX_XML_ELEMENTS,
                    line,
                });
            }
        }
    }
    Ok(())
}

/// A link: its name and inertial mass (kg, 0 when the URDF gives no `<inertial>`).
#[derive(Debug, Clone, PartialEq)]
pub struct Link {
    pub name: String,
    pub mass: f64,
}

/// How a movable joint moves its child link.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MotionKind {
    /// Rotation about the axis, within position limits.
    Revolute,
    /// Rotation about the axis, unlimited.
    Continuous,
    /// Translation along the axis.
    Prismatic,
}

/// Limits of a movable joint: position (rad or m; infinite for continuous joints), effort (N·m
/// or N) and velocity (rad/s or m/s), as the URDF `<limit>` gives them. A continuous joint may
/// omit `<limit>`: its effort and velocity are then unknown, given as infinite.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointLimits {
    pub lower: f64,
    pub upper: f64,
    pub effort: f64,
    pub velocity: f64,
}

impl JointLimits {
    /// Whether the URDF gave this joint's effort and velocity limits (a `<limit>` element):
    /// what anything that drives the joint needs.
    pub fn known_dynamics(&self) -> bool {
        self.effort.is_finite() && self.velocity.is_finite()
    }
}

/// The one degree of freedom of a movable joint.
#[derive(Debug, Clone, PartialEq)]
pub struct Motion {
    pub kind: MotionKind,
    /// Unit axis in the joint frame.
    pub axis: Unit<Vector3<f64>>,
    pub limits: JointLimits,
}

impl Motion {
    fn from_urdf(kind: MotionKind, joint: &urdf_rs::Joint) -> Result<Self> {
        let axis = joint.axis.xyz.0;
        let unit = Some(Vector3::from(axis))
            .filter(|a| a.iter().all(|v| v.is_finite()))
            .and_then(|a| Unit::try_new(a, f64::EPSILON))
            .ok_or_else(|| KinematicsError::BadAxis {
                joint: joint.name.clone(),
                axis,
            })?;
        // urdf_rs gives an absent `<limit>` as its default (all zero); `velocity` is required
        // in a `<limit>`, so a given one never equals it.
        let given = joint.limit != urdf_rs::JointLimit::default();
        if !given && kind != MotionKind::Continuous {
            return Err(KinematicsError::MissingLimit {
                joint: joint.name.clone(),
            });
        }
        let urdf_rs::JointLimit {
            mut lower,
            mut upper,
            mut effort,
            mut velocity,
            ..
        } = joint.limit;
        let bad = |field, value, expected| KinematicsError::BadJointValue {
            joint: joint.name.clone(),
            field,
            value,
            expected,
        };
        const NON_NEGATIVE: &str = "a finite number >= 0";
        if given {
            // Far above any actuator (a 1 MN·m joint, 1 km/s): beyond them the number is a
            // typo.
            for (field, value, max, expected) in [
                ("limit effort", effort, MAX_EFFORT, "in (0, 1e6] N·m or N"),
                (
                    "limit velocity",
                    velocity,
                    MAX_VELOCITY,
                    "in (0, 1000] rad/s or m/s",
                ),
            ] {
                if !(value.is_finite() && value > 0.0 && value <= max) {
                    return Err(bad(field, value, expected));
                }
            }
        } else {
            // A continuous joint without `<limit>` (many wheel joints): effort and velocity are
            // unknown, not zero. Kinematics needs neither; what drives the joint must ask
            // ([`JointLimits::known_dynamics`]).
            (effort, velocity) = (f64::INFINITY, f64::INFINITY);
        }
        if let Some(dynamics) = &joint.dynamics {
            for (field, value) in [
                ("dynamics damping", dynamics.damping),
                ("dynamics friction", dynamics.friction),
            ] {
                if !(value.is_finite() && value >= 0.0) {
                    return Err(bad(field, value, NON_NEGATIVE));
                }
            }
        }
        if kind == MotionKind::Continuous {
            // URDF continuous joints have no position limits, whatever `<limit>` says.
            (lower, upper) = (f64::NEG_INFINITY, f64::INFINITY);
        } else {
            // A revolute joint of more than 16 turns either way, or a prismatic one longer
            // than the largest model, is a typo.
            let (max, expected) = match kind {
                MotionKind::Prismatic => (physical::MAX_EXTENT_M, "finite, within ±1000 m"),
                _ => (MAX_REVOLUTE_RAD, "finite, within ±100 rad"),
            };
            for (field, value) in [("limit lower", lower), ("limit upper", upper)] {
                if !(value.is_finite() && value.abs() <= max) {
                    return Err(bad(field, value, expected));
                }
            }
            if lower > upper {
                return Err(KinematicsError::BadLimits {
                    joint: joint.name.clone(),
                    lower,
                    upper,
                });
            }
        }
        Ok(Motion {
            kind,
            axis: unit,
            limits: JointLimits {
                lower,
                upper,
                effort,
                velocity,
            },
        })
    }

    /// The joint frame → child link frame transform at joint value `q`.
    fn transform(&self, q: f64) -> Isometry3<f64> {
        match self.kind {
            MotionKind::Revolute | MotionKind::Continuous => Isometry3::from_parts(
                Translation3::identity(),
                UnitQuaternion::from_axis_angle(&self.axis, q),
            ),
            MotionKind::Prismatic => Translation3::from(self.axis.into_inner() * q).into(),
        }
    }
}

/// Largest joint effort limit, N·m or N.
const MAX_EFFORT: f64 = 1e6;
/// Largest joint velocity limit, rad/s or m/s.
const MAX_VELOCITY: f64 = 1e3;
/// Largest |position limit| of a revolute joint, rad (about 16 turns).
const MAX_REVOLUTE_RAD: f64 = 100.0;

/// A URDF `origin` (xyz, fixed-axis rpy) as an isometry: R = Rz(yaw)·Ry(pitch)·Rx(roll).
pub fn urdf_pose(pose: &urdf_rs::Pose) -> Isometry3<f64> {
    let [roll, pitch, yaw] = pose.rpy.0;
    Isometry3::from_parts(
        Translation3::from(Vector3::from(pose.xyz.0)),
        UnitQuaternion::from_euler_angles(roll, pitch, yaw),
    )
}

/// A validated joint.
#[derive(Debug, Clone, PartialEq)]
pub struct Joint {
    pub name: String,
    pub parent: String,
    pub child: String,
    /// Joint frame in the parent link frame.
    pub origin: Isometry3<f64>,
    /// `None` for a fixed joint (whose URDF axis is ignored, so it may be zero).
    pub motion: Option<Motion>,
}

impl Joint {
    /// The child link frame in the parent link frame at joint value `q` (rad or m; ignored
    /// for a fixed joint): `origin · M(q)`.
    pub fn child_in_parent(&self, q: f64) -> Isometry3<f64> {
        match &self.motion {
            Some(motion) => self.origin * motion.transform(q),
            None => self.origin,
        }
    }

    /// The URDF joint type: "fixed", "revolute", "continuous" or "prismatic".
    pub fn type_name(&self) -> &'static str {
        match self.motion.as_ref().map(|m| m.kind) {
            None => "fixed",
            Some(MotionKind::Revolute) => "revolute",
            Some(MotionKind::Continuous) => "continuous",
            Some(MotionKind::Prismatic) => "prismatic",
        }
    }

    fn from_urdf(joint: &urdf_rs::Joint) -> Result<Self> {
        let name = || joint.name.clone();
        let kind = match joint.joint_type {
            urdf_rs::JointType::Fixed => None,
            urdf_rs::JointType::Revolute => Some(MotionKind::Revolute),
            urdf_rs::JointType::Continuous => Some(MotionKind::Continuous),
            urdf_rs::JointType::Prismatic => Some(MotionKind::Prismatic),
            ref other => {
                return Err(KinematicsError::UnsupportedJointType {
                    joint: name(),
                    kind: format!("{other:?}").to_lowercase(),
                })
            }
        };
        if !physical::pose_is_finite(&joint.origin) {
            return Err(KinematicsError::NonFiniteOrigin { joint: name() });
        }
        let origin = urdf_pose(&joint.origin);
        let motion = kind
            .map(|kind| Motion::from_urdf(kind, joint))
            .transpose()?;
        Ok(Joint {
            name: name(),
            parent: joint.parent.link.clone(),
            child: joint.child.link.clone(),
            origin,
            motion,
        })
    }
}

/// A validated URDF kinematic tree: unique names, every joint between existing links, every
/// link but one root the child of exactly one joint, no cycles, supported joint types only.
#[derive(Debug, Clone)]
pub struct KinematicTree {
    name: String,
    links: Vec<Link>,
    joints: Vec<Joint>,
    link_ids: HashMap<String, usize>,
    /// Per link: (joint whose child it is, that joint's parent link); `None` for the root.
    parents: Vec<Option<(usize, usize)>>,
    /// Per link: (joint whose parent it is, that joint's child link), in URDF order.
    children: Vec<Vec<(usize, usize)>>,
    root: usize,
}

impl KinematicTree {
    /// Reads ([`read_urdf`]) and validates a URDF file; every error names the file.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        Self::from_robot(&read_urdf(path)?).map_err(|e| e.in_file(path))
    }

    /// Parses ([`parse_urdf`], with its XML caps) and validates URDF XML text.
    pub fn from_urdf_str(urdf: &str) -> Result<Self> {
        Self::from_robot(&parse_urdf(urdf)?)
    }

    /// Validates a parsed URDF: its structure (see [`KinematicTree`]), its size ([`MAX_LINKS`],
    /// [`MAX_JOINTS`]) and its physics (see the module docs). Linear in the size of the URDF.
    pub fn from_robot(robot: &urdf_rs::Robot) -> Result<Self> {
        for (what, count, max) in [
            ("links", robot.links.len(), MAX_LINKS),
            ("joints", robot.joints.len(), MAX_JOINTS),
        ] {
            if count > max {
                return Err(KinematicsError::TooMany { what, count, max });
            }
        }
        let mut link_ids = HashMap::with_capacity(robot.links.len());
        let mut links = Vec::with_capacity(robot.links.len());
        let unnamed = |element| KinematicsError::EmptyName { element };
        for link in &robot.links {
            if link.name.trim().is_empty() {
                return Err(unnamed("link"));
            }
            if link_ids.insert(link.name.clone(), links.len()).is_some() {
                return Err(KinematicsError::DuplicateLink {
                    link: link.name.clone(),
                });
            }
            physical::check_link(link)?;
            links.push(Link {
                name: link.name.clone(),
                mass: link.inertial.mass.value,
            });
        }

        let mut joint_names = HashSet::with_capacity(robot.joints.len());
        let mut joints: Vec<Joint> = Vec::with_capacity(robot.joints.len());
        let mut parents: Vec<Option<(usize, usize)>> = vec![None; links.len()];
        let mut children = vec![Vec::new(); links.len()];
        for urdf_joint in &robot.joints {
            if urdf_joint.name.trim().is_empty() {
                return Err(unnamed("joint"));
            }
            if !joint_names.insert(urdf_joint.name.as_str()) {
                return Err(KinematicsError::DuplicateJoint {
                    joint: urdf_joint.name.clone(),
                });
            }
            let joint = Joint::from_urdf(urdf_joint)?;
            let id_of = |link: &str| {
                link_ids
                    .get(link)
                    .copied()
                    .ok_or_else(|| KinematicsError::MissingLink {
                        joint: joint.name.clone(),
                        link: link.to_owned(),
                    })
            };
            let (parent, child) = (id_of(&joint.parent)?, id_of(&joint.child)?);
            if let Some((first, _)) = parents[child] {
                return Err(KinematicsError::TwoParents {
                    link: joint.child,
                    first: joints[first].name.clone(),
                    second: joint.name,
                });
            }
            parents[child] = Some((joints.len(), parent));
            children[parent].push((joints.len(), child));
            joints.push(joint);
        }

        if let Some(link) = find_cycle(&parents) {
            return Err(KinematicsError::Cycle {
                link: links[link].name.clone(),
            });
        }
        // Without cycles every non-empty forest has a root.
        let mut roots = (0..links.len()).filter(|&l| parents[l].is_none());
        let root = roots.next().ok_or(KinematicsError::NoLinks)?;
        if let Some(second) = roots.next() {
            return Err(KinematicsError::MultipleRoots {
                first: links[root].name.clone(),
                second: links[second].name.clone(),
            });
        }

        Ok(KinematicTree {
            name: robot.name.clone(),
            links,
            joints,
            link_ids,
            parents,
            children,
            root,
        })
    }

    /// The robot name from the URDF.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The root link: the one link that is no joint's child.
    pub fn root(&self) -> &Link {
        &self.links[self.root]
    }

    /// All links, in URDF order.
    pub fn links(&self) -> &[Link] {
        &self.links
    }

    /// All joints, in URDF order.
    pub fn joints(&self) -> &[Joint] {
        &self.joints
    }

    /// The link named `name`, if any.
    pub fn link(&self, name: &str) -> Option<&Link> {
        self.link_ids.get(name).map(|&id| &self.links[id])
    }

    /// The joint named `name`, if any.
    pub fn joint(&self, name: &str) -> Option<&Joint> {
        self.joints.iter().find(|j| j.name == name)
    }

    /// The joints whose parent is `link`, each with its child link, in URDF order.
    pub fn children(&self, link: &str) -> Result<impl ExactSizeIterator<Item = (&Joint, &Link)>> {
        let id = self.link_id(link)?;
        Ok(self.children[id]
            .iter()
            .map(|&(joint, child)| (&self.joints[joint], &self.links[child])))
    }

    /// Number of movable joints in the whole tree.
    pub fn dof(&self) -> usize {
        self.joints.iter().filter(|j| j.motion.is_some()).count()
    }

    /// Sum of all link masses (kg).
    pub fn total_mass(&self) -> f64 {
        self.links.iter().map(|l| l.mass).sum()
    }

    /// Prepares forward kinematics from `base` to `tip` (any two links; see the module docs).
    pub fn chain(&self, base: &str, tip: &str) -> Result<Chain> {
        let mut up = self.joints_to_root(self.link_id(base)?);
        let mut down = self.joints_to_root(self.link_id(tip)?);
        // Both lists end with the joints above the common ancestor; drop those.
        while up.last().is_some() && up.last() == down.last() {
            up.pop();
            down.pop();
        }
        let mut chain = Chain {
            start: Isometry3::identity(),
            joints: Vec::new(),
        };
        for &joint in &up {
            chain.push(&self.joints[joint], Direction::Inverse);
        }
        for &joint in down.iter().rev() {
            chain.push(&self.joints[joint], Direction::Forward);
        }
        Ok(chain)
    }

    fn link_id(&self, link: &str) -> Result<usize> {
        self.link_ids
            .get(link)
            .copied()
            .ok_or_else(|| KinematicsError::UnknownLink {
                link: link.to_owned(),
            })
    }

    /// The joints from `link` up to the root, nearest first.
    fn joints_to_root(&self, mut link: usize) -> Vec<usize> {
        let mut joints = Vec::new();
        while let Some((joint, parent)) = self.parents[link] {
            joints.push(joint);
            link = parent;
        }
        joints
    }
}

/// A link on a cycle of `parents` (each link has at most one parent), if any.
fn find_cycle(parents: &[Option<(usize, usize)>]) -> Option<usize> {
    let mut reaches_root = vec![false; parents.len()];
    let mut walk = Vec::new();
    for start in 0..parents.len() {
        walk.clear();
        let mut link = start;
        while !reaches_root[link] {
            if walk.len() > parents.len() {
                // More steps than links: we are going round a cycle, and `link` is on it.
                return Some(link);
            }
            walk.push(link);
            match parents[link] {
                Some((_, parent)) => link = parent,
                None => break,
            }
        }
        for &l in &walk {
            reaches_root[l] = true;
        }
    }
    None
}

/// Whether a chain traverses a joint from parent to child or, on its upward part, back.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Direction {
    Forward,
    Inverse,
}

/// A movable joint of a chain and the constant transform that follows it.
#[derive(Debug, Clone, PartialEq)]
struct ChainJoint {
    name: String,
    motion: Motion,
    direction: Direction,
    after: Isometry3<f64>,
}

/// Forward kinematics from a base link to a tip link, prepared by [`KinematicTree::chain`].
///
/// Fixed joints and origins are folded into constants, so the pose is
/// `start · M₁(±q₁) · after₁ · … · Mₙ(±qₙ) · afterₙ`, with `-q` for inversely traversed joints:
/// `(origin · M(q))⁻¹ = M(-q) · origin⁻¹`.
#[derive(Debug, Clone, PartialEq)]
pub struct Chain {
    start: Isometry3<f64>,
    joints: Vec<ChainJoint>,
}

impl Chain {
    /// Number of movable joints, i.e. of joint values [`Chain::forward`] takes.
    pub fn dof(&self) -> usize {
        self.joints.len()
    }

    /// Movable joint names in chain order (as traversed from base to tip).
    pub fn joint_names(&self) -> impl ExactSizeIterator<Item = &str> {
        self.joints.iter().map(|j| j.name.as_str())
    }

    /// An upper bound, in metres, on the distance from the base frame or from any movable
    /// joint's frame to the tip, for every joint value within the limits: the sum of the
    /// lengths of the constant offsets, plus the travel of prismatic joints.
    ///
    /// A joint velocity q̇ⱼ therefore moves the tip by at most |q̇ⱼ|·max(reach, 1) (lever arm of
    /// a rotation, or unit gain of a translation); the sync clamp uses this to bound how fast
    /// the task-space image of a command can change.
    pub fn reach_bound_m(&self) -> f64 {
        let offsets: f64 = std::iter::once(&self.start)
            .chain(self.joints.iter().map(|j| &j.after))
            .map(|t| t.translation.vector.norm())
            .sum();
        let travel: f64 = self
            .joints
            .iter()
            .filter(|j| j.motion.kind == MotionKind::Prismatic)
            .map(|j| j.motion.limits.lower.abs().max(j.motion.limits.upper.abs()))
            .sum();
        offsets + travel
    }

    /// Limits of the movable joints in chain order.
    pub fn limits(&self) -> impl ExactSizeIterator<Item = &JointLimits> {
        self.joints.iter().map(|j| &j.motion.limits)
    }

    /// The tip link frame expressed in the base link frame, for joint values `q` in chain order
    /// (rad or m, each the joint's own URDF position). Does not allocate.
    pub fn forward(&self, q: &[f64]) -> Result<Isometry3<f64>> {
        if q.len() != self.joints.len() {
            return Err(KinematicsError::WrongJointCount {
                expected: self.joints.len(),
                got: q.len(),
            });
        }
        Ok(self
            .joints
            .iter()
            .zip(q)
            .fold(self.start, |pose, (joint, &q)| {
                let q = match joint.direction {
                    Direction::Forward => q,
                    Direction::Inverse => -q,
                };
                pose * joint.motion.transform(q) * joint.after
            }))
    }

    /// Appends one joint traversal: `origin · M(q)` forward, `M(-q) · origin⁻¹` inverse.
    fn push(&mut self, joint: &Joint, direction: Direction) {
        if direction == Direction::Forward {
            self.append(&joint.origin);
        }
        if let Some(motion) = &joint.motion {
            self.joints.push(ChainJoint {
                name: joint.name.clone(),
                motion: motion.clone(),
                direction,
                after: Isometry3::identity(),
            });
        }
        if direction == Direction::Inverse {
            self.append(&joint.origin.inverse());
        }
    }

    /// Right-multiplies the constant that currently ends the chain.
    fn append(&mut self, transform: &Isometry3<f64>) {
        let last = match self.joints.last_mut() {
            Some(joint) => &mut joint.after,
            None => &mut self.start,
        };
        *last *= transform;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::f64::consts::FRAC_PI_2;

    fn tree(body: &str) -> Result<KinematicTree> {
        KinematicTree::from_urdf_str(&format!(r#"<robot name="test">{body}</robot>"#))
    }

    fn assert_pose_eq(a: &Isometry3<f64>, b: &Isometry3<f64>) {
        let delta = a.inverse() * b;
        assert!(
            delta.translation.vector.norm() < 1e-12 && delta.rotation.angle() < 1e-12,
            "{a} != {b}"
        );
    }

    #[test]
    fn reach_bound_dominates_every_tip_distance() {
        let tree = tree(PLANAR).unwrap();
        let chain = tree.chain("base", "hand").unwrap();
        assert!((chain.reach_bound_m() - 0.8).abs() < 1e-12);
        for q in [[0.0, 0.0], [1.0, -2.0], [-1.0, 3.0]] {
            assert!(chain.forward(&q).unwrap().translation.vector.norm() <= 0.8 + 1e-12);
        }
    }

    /// Planar arm in the xy plane: shoulder at the base origin, 0.5 m upper arm, 0.3 m forearm.
    const PLANAR: &str = r#"
        <link name="base"/><link name="upper"/><link name="fore"/><link name="hand"/>
        <joint name="shoulder" type="revolute">
            <parent link="base"/><child link="upper"/><axis xyz="0 0 1"/>
            <limit lower="-1" upper="1.5" effort="10" velocity="2"/>
        </joint>
        <joint name="elbow" type="continuous">
            <origin xyz="0.5 0 0"/><parent link="upper"/><child link="fore"/><axis xyz="0 0 2"/>
            <limit effort="5" velocity="3"/>
        </joint>
        <joint name="wrist" type="fixed">
            <origin xyz="0.3 0 0"/><parent link="fore"/><child link="hand"/><axis xyz="0 0 0"/>
        </joint>"#;

    #[test]
    fn planar_arm_matches_hand_computation() {
        let chain = tree(PLANAR).unwrap().chain("base", "hand").unwrap();
        assert_eq!(chain.dof(), 2);
        assert_eq!(
            chain.joint_names().collect::<Vec<_>>(),
            ["shoulder", "elbow"]
        );
        let (q1, q2) = (0.4_f64, -1.1_f64);
        let expected = Isometry3::new(
            Vector3::new(
                0.5 * q1.cos() + 0.3 * (q1 + q2).cos(),
                0.5 * q1.sin() + 0.3 * (q1 + q2).sin(),
                0.0,
            ),
            Vector3::z() * (q1 + q2),
        );
        assert_pose_eq(&chain.forward(&[q1, q2]).unwrap(), &expected);
    }

    #[test]
    fn joint_transforms_compose_to_the_chain() {
        let tree = tree(PLANAR).unwrap();
        let chain = tree.chain("base", "hand").unwrap();
        for q in [[0.0, 0.0], [0.4, -1.1], [-0.9, 2.5]] {
            let j = |name: &str| tree.joint(name).unwrap();
            let composed = j("shoulder").child_in_parent(q[0])
                * j("elbow").child_in_parent(q[1])
                * j("wrist").child_in_parent(123.0);
            assert_pose_eq(&composed, &chain.forward(&q).unwrap());
        }
    }

    #[test]
    fn tree_accessors_and_limits() {
        let tree = tree(PLANAR).unwrap();
        assert_eq!(tree.name(), "test");
        assert_eq!(tree.root().name, "base");
        assert_eq!(tree.dof(), 2);
        let children: Vec<_> = tree.children("upper").unwrap().collect();
        assert_eq!(children.len(), 1);
        assert_eq!(
            (&*children[0].0.name, &*children[0].1.name),
            ("elbow", "fore")
        );
        assert_eq!(tree.joint("wrist").unwrap().type_name(), "fixed");
        let elbow = tree.joint("elbow").unwrap().motion.as_ref().unwrap();
        assert_eq!(elbow.axis, Vector3::z_axis());
        let limits: Vec<_> = tree
            .chain("base", "hand")
            .unwrap()
            .limits()
            .copied()
            .collect();
        let shoulder = JointLimits {
            lower: -1.0,
            upper: 1.5,
            effort: 10.0,
            velocity: 2.0,
        };
        let elbow = JointLimits {
            lower: f64::NEG_INFINITY,
            upper: f64::INFINITY,
            effort: 5.0,
            velocity: 3.0,
        };
        assert_eq!(limits, [shoulder, elbow]);
    }

    #[test]
    fn rpy_is_fixed_axis_roll_then_pitch_then_yaw() {
        let tree = tree(
            r#"<link name="a"/><link name="b"/>
            <joint name="j" type="fixed">
                <origin xyz="1 2 3" rpy="0.3 -0.7 1.1"/><parent link="a"/><child link="b"/>
            </joint>"#,
        )
        .unwrap();
        let rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 1.1)
            * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), -0.7)
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.3);
        let expected = Isometry3::from_parts(Translation3::new(1.0, 2.0, 3.0), rotation);
        assert_pose_eq(
            &tree.chain("a", "b").unwrap().forward(&[]).unwrap(),
            &expected,
        );
    }

    #[test]
    fn prismatic_moves_along_axis_in_joint_frame() {
        // The joint frame is rolled by 90°, so its (normalized) y axis is the parent's z axis.
        let tree = tree(
            r#"<link name="a"/><link name="b"/>
            <joint name="slide" type="prismatic">
                <origin xyz="1 0 0" rpy="1.5707963267948966 0 0"/>
                <parent link="a"/><child link="b"/><axis xyz="0 2 0"/>
                <limit lower="0" upper="0.5" effort="100" velocity="0.1"/>
            </joint>"#,
        )
        .unwrap();
        let pose = tree.chain("a", "b").unwrap().forward(&[0.25]).unwrap();
        let expected = Isometry3::new(Vector3::new(1.0, 0.0, 0.25), Vector3::x() * FRAC_PI_2);
        assert_pose_eq(&pose, &expected);
    }

    #[test]
    fn axis_defaults_to_x_and_masses_default_to_zero() {
        let tree = tree(
            r#"<link name="a">
                <inertial><mass value="2.5"/>
                    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial>
            </link>
            <link name="b"/>
            <joint name="j" type="continuous"><parent link="a"/><child link="b"/>
                <limit effort="1" velocity="1"/></joint>"#,
        )
        .unwrap();
        let motion = tree.joint("j").unwrap().motion.as_ref().unwrap();
        assert_eq!(motion.axis, Vector3::x_axis());
        assert_eq!(tree.link("a").unwrap().mass, 2.5);
        assert_eq!(tree.link("b").unwrap().mass, 0.0);
        assert_eq!(tree.total_mass(), 2.5);
    }

    #[test]
    fn same_base_and_tip_is_identity() {
        let chain = tree(PLANAR).unwrap().chain("fore", "fore").unwrap();
        assert_eq!(chain.dof(), 0);
        assert_eq!(chain.forward(&[]).unwrap(), Isometry3::identity());
    }

    #[test]
    fn wrong_joint_count_is_rejected() {
        let chain = tree(PLANAR).unwrap().chain("base", "hand").unwrap();
        let err = chain.forward(&[0.1]).unwrap_err();
        assert!(matches!(
            err,
            KinematicsError::WrongJointCount {
                expected: 2,
                got: 1
            }
        ));
    }

    #[test]
    fn unknown_chain_link_is_named() {
        let err = tree(PLANAR).unwrap().chain("base", "nose").unwrap_err();
        assert!(matches!(err, KinematicsError::UnknownLink { link } if link == "nose"));
    }

    #[test]
    fn missing_link_names_joint_and_link() {
        let err = tree(
            r#"<link name="a"/>
            <joint name="j" type="fixed"><parent link="a"/><child link="ghost"/></joint>"#,
        )
        .unwrap_err();
        assert!(
            matches!(&err, KinematicsError::MissingLink { joint, link } if joint == "j" && link == "ghost")
        );
        assert_eq!(
            err.to_string(),
            r#"joint "j" refers to missing link "ghost""#
        );
    }

    #[test]
    fn cycle_is_rejected() {
        let err = tree(
            r#"<link name="root"/><link name="a"/><link name="b"/>
            <joint name="ab" type="fixed"><parent link="a"/><child link="b"/></joint>
            <joint name="ba" type="fixed"><parent link="b"/><child link="a"/></joint>"#,
        )
        .unwrap_err();
        assert!(matches!(err, KinematicsError::Cycle { link } if link == "a" || link == "b"));
    }

    #[test]
    fn two_parents_names_link_and_both_joints() {
        let err = tree(
            r#"<link name="a"/><link name="b"/><link name="c"/>
            <joint name="ac" type="fixed"><parent link="a"/><child link="c"/></joint>
            <joint name="bc" type="fixed"><parent link="b"/><child link="c"/></joint>"#,
        )
        .unwrap_err();
        assert!(
            matches!(err, KinematicsError::TwoParents { link, first, second }
            if link == "c" && first == "ac" && second == "bc")
        );
    }

    #[test]
    fn unsupported_joint_type_is_named() {
        for kind in ["floating", "planar", "spherical"] {
            let err = tree(&format!(
                r#"<link name="a"/><link name="b"/>
                <joint name="free" type="{kind}"><parent link="a"/><child link="b"/></joint>"#
            ))
            .unwrap_err();
            assert!(
                matches!(&err, KinematicsError::UnsupportedJointType { joint, kind: k }
                    if joint == "free" && k == kind),
                "{err}"
            );
        }
    }

    #[test]
    fn duplicate_names_are_rejected() {
        let err = tree(r#"<link name="a"/><link name="a"/>"#).unwrap_err();
        assert!(matches!(err, KinematicsError::DuplicateLink { link } if link == "a"));
        let err = tree(
            r#"<link name="a"/><link name="b"/><link name="c"/>
            <joint name="j" type="fixed"><parent link="a"/><child link="b"/></joint>
            <joint name="j" type="fixed"><parent link="b"/><child link="c"/></joint>"#,
        )
        .unwrap_err();
        assert!(matches!(err, KinematicsError::DuplicateJoint { joint } if joint == "j"));
    }

    #[test]
    fn bad_axis_origin_and_limits_are_rejected() {
        let joint = |attrs: &str| {
            tree(&format!(
                r#"<link name="a"/><link name="b"/>
                <joint name="j" type="revolute"><parent link="a"/><child link="b"/>{attrs}
                    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>"#
            ))
        };
        for axis in ["0 0 0", "nan 0 1", "inf 0 0"] {
            let err = joint(&format!(r#"<axis xyz="{axis}"/>"#)).unwrap_err();
            assert!(matches!(err, KinematicsError::BadAxis { joint, .. } if joint == "j"));
        }
        for origin in [r#"xyz="nan 0 0""#, r#"rpy="0 inf 0""#] {
            let err = joint(&format!("<origin {origin}/>")).unwrap_err();
            assert!(matches!(err, KinematicsError::NonFiniteOrigin { joint } if joint == "j"));
        }
        let err = tree(
            r#"<link name="a"/><link name="b"/>
            <joint name="j" type="prismatic"><parent link="a"/><child link="b"/>
                <limit lower="1" upper="-1" effort="1" velocity="1"/></joint>"#,
        )
        .unwrap_err();
        assert!(matches!(err, KinematicsError::BadLimits { joint, .. } if joint == "j"));
    }

    #[test]
    fn root_count_is_checked() {
        let err = tree(r#"<link name="a"/><link name="b"/>"#).unwrap_err();
        assert!(
            matches!(err, KinematicsError::MultipleRoots { first, second }
            if first == "a" && second == "b")
        );
        assert!(matches!(tree("").unwrap_err(), KinematicsError::NoLinks));
    }

    #[test]
    fn parse_errors_keep_the_file_path() {
        let err = KinematicTree::from_file("/nonexistent/robot.urdf").unwrap_err();
        assert!(err.to_string().contains("/nonexistent/robot.urdf"), "{err}");
    }

    /// Two branches off `root`: root →a (revolute) →b (prismatic) →c (fixed), root →d
    /// (continuous) →e (revolute); origins with rotations, axes not unit length.
    const BRANCHED: &str = r#"
        <link name="root"/><link name="a"/><link name="b"/><link name="c"/>
        <link name="d"/><link name="e"/>
        <joint name="ra" type="revolute">
            <origin xyz="0.1 -0.2 0.3" rpy="0.4 0.5 -0.6"/><parent link="root"/><child link="a"/>
            <axis xyz="1 2 3"/><limit lower="-3" upper="3" effort="1" velocity="1"/>
        </joint>
        <joint name="ab" type="prismatic">
            <origin xyz="0 0.5 0" rpy="-1 0.2 0"/><parent link="a"/><child link="b"/>
            <axis xyz="0 1 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/>
        </joint>
        <joint name="bc" type="fixed">
            <origin xyz="0.2 0 0.1" rpy="0 0 1.2"/><parent link="b"/><child link="c"/>
        </joint>
        <joint name="rd" type="continuous">
            <origin xyz="-0.3 0 0.2" rpy="0.1 0 0"/><parent link="root"/><child link="d"/>
            <axis xyz="-1 0 1"/><limit effort="1" velocity="1"/>
        </joint>
        <joint name="de" type="revolute">
            <origin xyz="0 0 0.4" rpy="0 1 0"/><parent link="d"/><child link="e"/>
            <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/>
        </joint>"#;

    #[test]
    fn chain_order_goes_up_then_down() {
        let tree = tree(BRANCHED).unwrap();
        let names: Vec<_> = tree
            .chain("c", "e")
            .unwrap()
            .joint_names()
            .map(String::from)
            .collect();
        assert_eq!(names, ["ab", "ra", "rd", "de"]);
        let names: Vec<_> = tree
            .chain("a", "c")
            .unwrap()
            .joint_names()
            .map(String::from)
            .collect();
        assert_eq!(names, ["ab"]);
    }

    proptest! {
        #[test]
        fn reversed_chain_is_inverse_and_matches_root_chains(
            q in proptest::collection::vec(-3.0..3.0f64, 4)
        ) {
            let tree = tree(BRANCHED).unwrap();
            let c_to_e = tree.chain("c", "e").unwrap().forward(&q).unwrap();
            let reversed: Vec<f64> = q.iter().rev().copied().collect();
            let e_to_c = tree.chain("e", "c").unwrap().forward(&reversed).unwrap();
            assert_pose_eq(&(c_to_e * e_to_c), &Isometry3::identity());

            // Independently through two downward chains from the root: T_ce = T_rc⁻¹ · T_re.
            let root_c = tree.chain("root", "c").unwrap().forward(&[q[1], q[0]]).unwrap();
            let root_e = tree.chain("root", "e").unwrap().forward(&q[2..]).unwrap();
            assert_pose_eq(&c_to_e, &(root_c.inverse() * root_e));
        }
    }
}
