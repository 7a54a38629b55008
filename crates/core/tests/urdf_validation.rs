//! URDF validation, one test per class of bad input: non-finite values, values out of range,
//! inertias no rigid body has, impossible geometry, XML too deep or too large, files too
//! large, too many links; and kinematic chains far deeper than any robot's, which must load
//! and evaluate without recursion.

use std::path::Path;
use std::time::Instant;

use moonhaul_core::input::{InputError, MAX_URDF_BYTES};
use moonhaul_core::kinematics::{
    parse_urdf, read_urdf, KinematicTree, KinematicsError, MAX_LINKS, MAX_XML_DEPTH,
    MAX_XML_ELEMENTS,
};

fn tree(body: &str) -> Result<KinematicTree, KinematicsError> {
    KinematicTree::from_urdf_str(&format!(r#"<robot name="test">{body}</robot>"#))
}

/// A link `arm` with the given `<inertial>` contents.
fn inertial(contents: &str) -> String {
    format!(r#"<link name="arm"><inertial>{contents}</inertial></link>"#)
}

/// `<mass>` and `<inertia>` (ixx, ixy, ixz, iyy, iyz, izz).
fn inertia(mass: &str, values: [&str; 6]) -> String {
    let [ixx, ixy, ixz, iyy, iyz, izz] = values;
    format!(
        r#"<mass value="{mass}"/><inertia ixx="{ixx}" ixy="{ixy}" ixz="{ixz}" iyy="{iyy}" iyz="{iyz}" izz="{izz}"/>"#
    )
}

const UNIT: [&str; 6] = ["1", "0", "0", "1", "0", "1"];

/// Links `a` → `b` by a joint `j` of `kind` with the given `<limit>`/`<dynamics>` elements.
fn joint(kind: &str, elements: &str) -> String {
    format!(
        r#"<link name="a"/><link name="b"/>
        <joint name="j" type="{kind}"><parent link="a"/><child link="b"/>{elements}</joint>"#
    )
}

fn limit(lower: &str, upper: &str, effort: &str, velocity: &str) -> String {
    format!(r#"<limit lower="{lower}" upper="{upper}" effort="{effort}" velocity="{velocity}"/>"#)
}

/// A link `shape` with one `<collision>` (or `<visual>`) of the given geometry and origin.
fn geometry(element: &str, origin: &str, geometry: &str) -> String {
    format!(
        r#"<link name="shape"><{element}><origin {origin}/><geometry>{geometry}</geometry></{element}></link>"#
    )
}

/// Asserts that `body` is rejected and that the message names every one of `names`.
fn assert_rejected(body: &str, names: &[&str]) -> KinematicsError {
    let err = tree(body).expect_err(body);
    let message = err.to_string();
    for name in names {
        assert!(message.contains(name), "{message:?} should name {name:?}");
    }
    err
}

fn chain_urdf(links: usize) -> String {
    let mut urdf = String::from(r#"<robot name="chain"><link name="l0"/>"#);
    for i in 1..links {
        urdf += &format!(
            r#"<link name="l{i}"/><joint name="j{i}" type="revolute"><origin xyz="0 0 0.01"/>
            <parent link="l{}"/><child link="l{i}"/><axis xyz="0 1 0"/>
            <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>"#,
            i - 1
        );
    }
    urdf + "</robot>"
}

#[test]
fn valid_physics_is_accepted() {
    // Point mass, thin rod (triangle equality), massless frame (zero mass and inertia, what
    // urdf_rs reads for a link without <inertial>), rotated inertia with products, a mirrored mesh, every shape, dynamics, continuous
    // joint limits.
    let tree = tree(&format!(
        r#"{}<link name="rod"><inertial>{}</inertial></link>
        <link name="frame"><inertial><mass value="0"/>
            <inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial></link>
        <link name="tilted"><inertial><origin xyz="0 0 0.1" rpy="0 0.5 0"/>{}</inertial>
            <visual><geometry><mesh filename="m.obj" scale="-1 1 2"/></geometry></visual>
            <visual><geometry><cylinder radius="0.1" length="0.2"/></geometry></visual>
            <collision><geometry><sphere radius="0.1"/></geometry></collision>
            <collision><geometry><box size="0.1 0.2 0.3"/></geometry></collision>
            <collision><geometry><capsule radius="0.1" length="0.2"/></geometry></collision>
        </link>
        <joint name="j1" type="fixed"><parent link="arm"/><child link="rod"/></joint>
        <joint name="j2" type="continuous"><parent link="arm"/><child link="frame"/>
            <limit effort="3" velocity="4"/><dynamics damping="0.5" friction="0"/></joint>
        <joint name="j3" type="revolute"><parent link="arm"/><child link="tilted"/>
            {}<dynamics damping="0"/></joint>"#,
        inertial(&inertia("1", ["0"; 6])),
        inertia("1", ["1", "0", "0", "1", "0", "0"]),
        inertia("1", ["2", "0.5", "0.1", "2", "-0.2", "1.5"]),
        limit("-1", "1", "10", "2"),
    ))
    .unwrap();
    assert_eq!(tree.total_mass(), 3.0);
    assert_eq!(tree.link("frame").unwrap().mass, 0.0);
}

#[test]
fn a_continuous_joint_without_limit_has_unknown_dynamics_not_zero() {
    let wheel = tree(&joint("continuous", r#"<axis xyz="0 1 0"/>"#)).unwrap();
    let limits = wheel.joint("j").unwrap().motion.as_ref().unwrap().limits;
    assert!(!limits.known_dynamics(), "{limits:?}");
    assert_eq!(
        (limits.lower, limits.upper),
        (f64::NEG_INFINITY, f64::INFINITY)
    );
    // Kinematics needs none: the wheel turns.
    let chain = wheel.chain("a", "b").unwrap();
    let pose = chain.forward(&[std::f64::consts::FRAC_PI_2]).unwrap();
    assert!((pose.rotation.angle() - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    // With a `<limit>`, its values are known and checked.
    let limited = tree(&joint("continuous", &limit("0", "0", "3", "4"))).unwrap();
    let limits = limited.joint("j").unwrap().motion.as_ref().unwrap().limits;
    assert!(limits.known_dynamics() && limits.effort == 3.0 && limits.velocity == 4.0);
}

#[test]
fn non_finite_values_are_rejected_naming_the_element() {
    let cases = [
        (inertial(&inertia("nan", UNIT)), vec!["\"arm\"", "mass"]),
        (
            inertial(&inertia("1", ["1", "0", "inf", "1", "0", "1"])),
            vec!["\"arm\"", "inertia ixz"],
        ),
        (
            inertial(&format!(r#"<origin xyz="0 nan 0"/>{}"#, inertia("1", UNIT))),
            vec!["\"arm\"", "origin"],
        ),
        (
            joint("revolute", &limit("-inf", "1", "1", "1")),
            vec!["\"j\"", "limit lower"],
        ),
        (
            joint("prismatic", &limit("0", "nan", "1", "1")),
            vec!["\"j\"", "limit upper"],
        ),
        (
            joint("revolute", &limit("-1", "1", "inf", "1")),
            vec!["\"j\"", "limit effort"],
        ),
        (
            joint("continuous", &limit("0", "0", "1", "nan")),
            vec!["\"j\"", "limit velocity"],
        ),
        (
            joint(
                "revolute",
                &format!(r#"{}<dynamics damping="inf"/>"#, limit("-1", "1", "1", "1")),
            ),
            vec!["\"j\"", "dynamics damping"],
        ),
        (
            geometry("collision", r#"rpy="0 0 inf""#, r#"<sphere radius="1"/>"#),
            vec!["\"shape\"", "collision #1", "origin"],
        ),
        (
            geometry("visual", "", r#"<box size="1 inf 1"/>"#),
            vec!["\"shape\"", "visual #1", "box size"],
        ),
        (
            geometry("visual", "", r#"<mesh filename="m.obj" scale="1 nan 1"/>"#),
            vec!["\"shape\"", "mesh scale"],
        ),
    ];
    for (body, names) in cases {
        let err = assert_rejected(&body, &names);
        assert!(
            matches!(
                err,
                KinematicsError::BadInertial { .. }
                    | KinematicsError::BadJointValue { .. }
                    | KinematicsError::BadGeometry { .. }
            ),
            "{err:?}"
        );
    }
}

#[test]
fn out_of_range_values_are_rejected_naming_the_element() {
    let cases = [
        (inertial(&inertia("-1", UNIT)), vec!["\"arm\"", "mass -1"]),
        (
            inertial(&inertia("0", UNIT)),
            vec!["\"arm\"", "mass is 0 kg but the inertia is not zero"],
        ),
        (
            joint("revolute", &limit("-1", "1", "0", "1")),
            vec!["\"j\"", "limit effort is 0"],
        ),
        (
            joint("prismatic", &limit("0", "1", "1", "-2")),
            vec!["\"j\"", "limit velocity is -2"],
        ),
        // Revolute and prismatic joints need their `<limit>` (URDF requires it of them).
        (joint("revolute", ""), vec!["\"j\"", "has no <limit>"]),
        (joint("prismatic", ""), vec!["\"j\"", "has no <limit>"]),
        (
            joint(
                "continuous",
                &format!(
                    r#"{}<dynamics friction="-0.1"/>"#,
                    limit("0", "0", "1", "1")
                ),
            ),
            vec!["\"j\"", "dynamics friction is -0.1"],
        ),
        (
            joint("revolute", &limit("1", "-1", "1", "1")),
            vec!["\"j\"", "lower 1, upper -1"],
        ),
    ];
    for (body, names) in cases {
        assert_rejected(&body, &names);
    }
    // Limits of fixed joints are ignored.
    tree(&joint("fixed", &limit("1", "-1", "0", "-1"))).unwrap();
}

#[test]
fn inertia_no_rigid_body_has_is_rejected() {
    let cases = [
        (
            "1",
            ["-1", "0", "0", "1", "0", "1"],
            "not positive semi-definite",
        ),
        // Positive diagonal, but the products make it indefinite.
        (
            "1",
            ["1", "2", "0", "1", "0", "1"],
            "not positive semi-definite",
        ),
        ("1", ["1", "0", "0", "1", "0", "3"], "triangle inequality"),
        // A zero mass with any inertia is a contradiction, not a frame link.
        (
            "0",
            ["1", "0", "0", "1", "0", "-3"],
            "mass is 0 kg but the inertia is not zero",
        ),
    ];
    for (mass, values, reason) in cases {
        let err = assert_rejected(&inertial(&inertia(mass, values)), &["\"arm\"", reason]);
        assert!(
            matches!(&err, KinematicsError::BadInertial { link, .. } if link == "arm"),
            "{err:?}"
        );
    }
}

#[test]
fn impossible_geometry_is_rejected() {
    let cases = [
        (r#"<box size="1 0 1"/>"#, "box size"),
        (r#"<sphere radius="-0.1"/>"#, "sphere radius -0.1"),
        (r#"<cylinder radius="0.1" length="0"/>"#, "cylinder"),
        (r#"<capsule radius="0" length="1"/>"#, "capsule"),
        (r#"<mesh filename="m.obj" scale="1 0 1"/>"#, "mesh scale"),
    ];
    for (shape, reason) in cases {
        for element in ["visual", "collision"] {
            let err = assert_rejected(&geometry(element, "", shape), &["\"shape\"", reason]);
            assert!(
                matches!(&err, KinematicsError::BadGeometry { link, element: e, .. }
                    if link == "shape" && e == &format!("{element} #1")),
                "{err:?}"
            );
        }
    }
    // A named element is named by its name.
    let err = tree(
        r#"<link name="shape"><collision name="bumper"><geometry><sphere radius="0"/></geometry>
        </collision></link>"#,
    )
    .unwrap_err();
    assert!(err.to_string().contains(r#"collision "bumper""#), "{err}");
}

#[test]
fn too_deep_xml_is_rejected_before_parsing() {
    let nested = |depth: usize| "<x>".repeat(depth) + &"</x>".repeat(depth);
    // robot + link + nesting: exactly at the cap is only rejected by urdf_rs, as unknown XML
    // inside a link is ignored.
    let at_cap = format!(
        r#"<robot name="r"><link name="a">{}</link></robot>"#,
        nested(MAX_XML_DEPTH - 2)
    );
    parse_urdf(&at_cap).unwrap();
    let over = format!(
        r#"<robot name="r"><link name="a">{}</link></robot>"#,
        nested(MAX_XML_DEPTH - 1)
    );
    assert!(matches!(
        parse_urdf(&over),
        Err(KinematicsError::XmlTooDeep {
            max: MAX_XML_DEPTH,
            line: 1
        })
    ));
    // Far too deep for any recursive parser: still a clean error.
    let err = parse_urdf(&format!(r#"<robot name="r">{}</robot>"#, nested(1_000_000))).unwrap_err();
    assert!(matches!(err, KinematicsError::XmlTooDeep { .. }), "{err}");

    // Markup-like text inside comments, CDATA, processing instructions, DOCTYPE and attribute
    // values neither hides nesting nor counts as elements.
    let decoys = r#"<?xml version="1.0"?><!DOCTYPE robot>
        <!-- </x></x> --><?pi </x> ? ><![CDATA[</x></x>]]>"#;
    let level = r#"<x><!-- </x> --><![CDATA[</x>]]><?p </x> ? ><y v='</x>' w="/>"/>"#;
    let tricky = format!(
        r#"{decoys}<robot name="a>b</x>'"><link name="c/>d">{}{}</link></robot>"#,
        level.repeat(MAX_XML_DEPTH),
        "</x>".repeat(MAX_XML_DEPTH)
    );
    let err = parse_urdf(&tricky).unwrap_err();
    assert!(
        matches!(err, KinematicsError::XmlTooDeep { line: 2, .. }),
        "{err}"
    );
    // urdf_rs's XML parser ends a processing instruction at the first '>' after any '?' and
    // takes '>' as part of an attribute name; a scanner that ended them elsewhere would miss
    // the nesting after them.
    for quirk in [r#"<?p ? >"#, r#"<z a>b="<!--"/>"#] {
        let hidden = format!(
            r#"<robot name="r"><link name="l">{quirk}{}?>--></link></robot>"#,
            nested(MAX_XML_DEPTH)
        );
        let err = parse_urdf(&hidden).unwrap_err();
        assert!(
            matches!(err, KinematicsError::XmlTooDeep { .. }),
            "{quirk}: {err}"
        );
        // The parser does see what follows.
        let visible = format!(r#"<robot name="r">{quirk}<link name="seen"/>?>--></robot>"#);
        assert_eq!(
            parse_urdf(&visible).unwrap().links[0].name,
            "seen",
            "{quirk}"
        );
    }
    let shallow = format!(
        r#"{decoys}<robot name="a>b</x>'"><link name="c/>d"><!-- {0} --><y v='{0}'/></link></robot>"#,
        "<x>".repeat(2 * MAX_XML_DEPTH)
    );
    let robot = parse_urdf(&shallow).unwrap();
    assert_eq!(robot.links[0].name, "c/>d");
}

#[test]
fn too_many_xml_elements_are_rejected_before_parsing() {
    let flat = |count: usize| format!(r#"<robot name="r">{}</robot>"#, "<x/>".repeat(count));
    assert!(parse_urdf(&flat(MAX_XML_ELEMENTS - 1)).is_ok());
    let err = parse_urdf(&flat(MAX_XML_ELEMENTS)).unwrap_err();
    assert!(
        matches!(
            err,
            KinematicsError::XmlTooManyElements {
                max: MAX_XML_ELEMENTS,
                ..
            }
        ),
        "{err}"
    );
}

#[test]
fn oversized_or_unreadable_files_are_rejected_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let big = dir.path().join("big.urdf");
    let mut text = String::from(r#"<robot name="r"><link name="a"/>"#);
    text += &" ".repeat(MAX_URDF_BYTES as usize);
    std::fs::write(&big, text + "</robot>").unwrap();
    let err = read_urdf(&big).unwrap_err();
    assert!(
        matches!(&err, KinematicsError::Input(InputError::TooLarge { .. })),
        "{err}"
    );
    assert!(err.to_string().contains("big.urdf"), "{err}");
    let err = KinematicTree::from_file(dir.path()).unwrap_err();
    assert!(
        matches!(&err, KinematicsError::Input(InputError::NotAFile { .. })),
        "{err}"
    );

    // Errors past reading name the file and the element.
    let bad = dir.path().join("bad.urdf");
    std::fs::write(
        &bad,
        format!(
            r#"<robot name="r">{}</robot>"#,
            inertial(&inertia("-2", UNIT))
        ),
    )
    .unwrap();
    let err = KinematicTree::from_file(&bad).unwrap_err();
    let message = err.to_string();
    assert!(
        message.contains("bad.urdf") && message.contains(r#"link "arm""#),
        "{message}"
    );
    assert!(
        matches!(err.without_file(), KinematicsError::BadInertial { .. }),
        "{err:?}"
    );
    std::fs::write(&bad, "<robot name=").unwrap();
    let err = read_urdf(&bad).unwrap_err();
    assert!(
        matches!(err.without_file(), KinematicsError::Parse(_)),
        "{err:?}"
    );
    assert!(err.to_string().contains("bad.urdf"), "{err}");
}

#[test]
fn too_many_links_are_rejected() {
    let links: String = (0..=MAX_LINKS)
        .map(|i| format!(r#"<link name="l{i}"/>"#))
        .collect();
    let err = tree(&links).unwrap_err();
    assert!(
        matches!(err, KinematicsError::TooMany { what: "links", count, max: MAX_LINKS }
            if count == MAX_LINKS + 1),
        "{err}"
    );
}

#[test]
fn chain_of_max_links_loads_and_evaluates_without_recursion() {
    // Test threads have small stacks, so recursion per link would overflow here.
    let urdf = chain_urdf(MAX_LINKS);
    let start = Instant::now();
    let tree = KinematicTree::from_urdf_str(&urdf).unwrap();
    let loaded = start.elapsed();
    assert_eq!((tree.links().len(), tree.dof()), (MAX_LINKS, MAX_LINKS - 1));
    let tip = format!("l{}", MAX_LINKS - 1);
    let chain = tree.chain("l0", &tip).unwrap();
    let pose = chain.forward(&vec![0.0; MAX_LINKS - 1]).unwrap();
    assert!((pose.translation.z - 0.01 * (MAX_LINKS - 1) as f64).abs() < 1e-9);
    let back = tree.chain(&tip, "l0").unwrap();
    assert_eq!(back.dof(), MAX_LINKS - 1);
    eprintln!(
        "{MAX_LINKS}-link chain ({} kB): parsed and validated at {:.0} links/s",
        urdf.len() / 1000,
        MAX_LINKS as f64 / loaded.as_secs_f64()
    );

    // The same ring without a root: the cycle search walks it without recursion.
    let ring = urdf.replace("</robot>", &format!(
        r#"<joint name="close" type="fixed"><parent link="{tip}"/><child link="l0"/></joint></robot>"#
    ));
    let err = KinematicTree::from_urdf_str(&ring).unwrap_err();
    assert!(matches!(err, KinematicsError::Cycle { .. }), "{err}");
}

#[test]
fn shipped_and_test_urdfs_pass_every_check() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut files: Vec<_> = std::fs::read_dir(root.join("assets"))
        .unwrap()
        .map(|entry| entry.unwrap().path())
        .filter(|path| path.extension().is_some_and(|e| e == "urdf"))
        .collect();
    files.push(root.join("crates/core/tests/data/panda.urdf"));
    assert!(files.len() >= 7, "{files:?}");
    for file in files {
        KinematicTree::from_file(&file).unwrap_or_else(|e| panic!("{e}"));
    }
}

#[test]
fn implausible_scales_and_empty_names_are_rejected() {
    let far = r#"<link name="a"/><link name="b"/>
        <joint name="j" type="fixed"><origin xyz="2000 0 0"/><parent link="a"/><child link="b"/></joint>"#;
    let cases = [
        (
            inertial(&inertia("1e9", UNIT)),
            vec!["\"arm\"", "exceeds"],
        ),
        (far.to_owned(), vec!["\"j\"", "1000 m"]),
        (
            geometry("collision", r#"xyz="0 0 0""#, r#"<box size="5000 1 1"/>"#),
            vec!["\"shape\"", "box size"],
        ),
        (
            geometry("visual", r#"xyz="0 0 1e6""#, r#"<sphere radius="1"/>"#),
            vec!["\"shape\"", "origin"],
        ),
        (
            joint("revolute", &limit("-1e6", "1", "1", "1")),
            vec!["\"j\"", "limit lower"],
        ),
        (
            joint("prismatic", &limit("0", "1", "1", "1e9")),
            vec!["\"j\"", "limit velocity"],
        ),
        (
            joint("continuous", &limit("0", "0", "1e300", "1")),
            vec!["\"j\"", "limit effort"],
        ),
        (r#"<link name=""/>"#.to_owned(), vec!["link has an empty name"]),
        (
            r#"<link name="a"/><link name="b"/><joint name=" " type="fixed"><parent link="a"/><child link="b"/></joint>"#
                .to_owned(),
            vec!["joint has an empty name"],
        ),
    ];
    for (body, names) in cases {
        assert_rejected(&body, &names);
    }
}
