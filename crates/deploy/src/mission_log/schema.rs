//! JSON schemas of the records, so Foxglove lists and plots their fields.

use moonhaul_coord::message::RejectCounts;

/// JSON Schema (draft 2020-12) of [`TickRecord`] as serde writes it, for Foxglove's field list.
/// A test keeps its property names equal to the struct's fields.
pub(super) fn tick_schema() -> serde_json::Value {
    use serde_json::json;
    let number = json!({ "type": "number" });
    let uint = json!({ "type": "integer", "minimum": 0 });
    let numbers = |n: usize| json!({ "type": "array", "items": { "type": "number" }, "minItems": n, "maxItems": n });
    let command = json!({
        "type": "object",
        "properties": {
            "wheel_velocity_radps": numbers(2),
            "arm_position_rad": numbers(7),
        }
    });
    let joints = |n: usize| {
        json!({
            "type": "object",
            "properties": { "position_rad": numbers(n), "velocity_radps": numbers(n) }
        })
    };
    let state = json!({
        "type": "object",
        "properties": {
            "wheels": joints(2),
            "arm": joints(7),
            "base_pose": {
                "type": "object",
                "properties": { "x_m": number, "y_m": number, "yaw_rad": number }
            },
            "base_velocity": {
                "type": "object",
                "properties": { "forward_mps": number, "yaw_rate_radps": number }
            }
        }
    });
    // The reject counters follow the struct (coord adds reasons as the protocol grows).
    let counts: serde_json::Map<String, serde_json::Value> =
        match serde_json::to_value(RejectCounts::default()) {
            Ok(serde_json::Value::Object(fields)) => {
                fields.into_iter().map(|(k, _)| (k, uint.clone())).collect()
            }
            _ => serde_json::Map::new(),
        };
    json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "moonhaul.TickRecord",
        "description": "One control tick of one unit (moonhaul-deploy record::TickRecord).",
        "type": "object",
        "properties": {
            "unit": uint,
            "tick": uint,
            "stamp_us": uint,
            "phase": phase_schema(),
            "hold": {
                "description": "Why the clamp held (null: it issued T(t_max)).",
                "type": ["string", "object", "null"]
            },
            "t_max": number,
            "distance": {
                "type": ["object", "null"],
                "properties": {
                    "value": number,
                    "binding": { "type": "object", "description": "{\"arm\": i} or {\"base\": i}" }
                }
            },
            "tracking_d": {
                "description": "This unit's d(U_{k-1}, Y_k) in tolerance units.",
                "type": ["number", "null"]
            },
            "sensed": state,
            "payload_height_estimate_m": { "type": ["number", "null"] },
            "press_m": {
                "description": "The largest height of a unit's sensed over its commanded end effector, the touchdown signal, m.",
                "type": ["number", "null"]
            },
            "goal_distance_m": number,
            "team_sensed": { "type": "array", "items": state.clone() },
            "team_previous": { "type": "array", "items": command.clone() },
            "grasp_force_n": { "type": ["number", "null"] },
            "grasp_open": { "type": "boolean" },
            "target": command,
            "issued": command,
            "peer_age_us": {
                "type": "array",
                "items": { "type": ["integer", "null"], "minimum": 0 }
            },
            "fault": { "type": ["string", "null"] },
            "rejected": { "type": "object", "properties": counts },
            "deadline_misses": uint,
            "work_us": uint,
        }
    })
}

/// JSON Schema of [`WorldFrame`]; a test keeps its property names equal to the struct's fields.
pub(super) fn world_schema() -> serde_json::Value {
    use serde_json::json;
    let number = json!({ "type": "number" });
    let uint = json!({ "type": "integer", "minimum": 0 });
    let numbers = |n: usize| json!({ "type": "array", "items": { "type": "number" }, "minItems": n, "maxItems": n });
    json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "moonhaul.WorldFrame",
        "description": "One world step: ground truth (moonhaul-deploy record::WorldFrame).",
        "type": "object",
        "properties": {
            "tick": uint,
            "stamp_us": uint,
            "payload_position_m": numbers(3),
            "payload_orientation_xyzw": numbers(4),
            "payload_height_m": number,
            "payload_tilt_deg": number,
            "payload_ground_contact": { "type": "boolean" },
            "base_position_m": { "type": "array", "items": numbers(3) },
            "base_orientation_xyzw": { "type": "array", "items": numbers(4) },
            "wheel_position_rad": { "type": "array", "items": numbers(2) },
            "arm_position_rad": { "type": "array", "items": numbers(7) },
            "unit_phase": {
                "type": "array",
                "items": { "anyOf": [phase_schema(), { "type": "null" }] }
            },
            "grasp_closed": { "type": "array", "items": { "type": "boolean" } },
        }
    })
}

fn phase_schema() -> serde_json::Value {
    serde_json::json!({ "type": "string", "enum": ["idle", "lift", "transport", "place"] })
}
