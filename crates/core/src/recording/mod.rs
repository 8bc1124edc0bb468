//! Recording format v1 (the contract `recording-format.md`): the message types of every topic,
//! their JSON Schemas and lenient parsing of detections, as plain data. Reading and writing
//! MCAP files is the `driftwatch-recording` crate's (`mcap_io`).

use std::collections::BTreeMap;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::measurement::Axis;

pub const TOPIC_INFO: &str = "/machine/info";
pub const TOPIC_STATE: &str = "/machine/state";
pub const TOPIC_SPINDLE: &str = "/spindle";
pub const TOPIC_TEMPERATURE: &str = "/temperature";
pub const TOPIC_DISPLACEMENT: &str = "/displacement";
pub const TOPIC_DETECTION: &str = "/probe/detection";
pub const TOPIC_RESULT: &str = "/cycle/result";
pub const TOPIC_COMPENSATION: &str = "/compensation";
/// The simulator's ground truth (a project topic; readers of the contract ignore it).
pub const TOPIC_TRUTH: &str = "/sim/truth";
/// R-test runs (an extension: `docs/recording-format.md`): one set-up per run, its readings.
pub const TOPIC_RTEST_SETUP: &str = "/rtest/setup";
pub const TOPIC_RTEST_READING: &str = "/rtest/reading";

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct MachineInfo {
    pub machine_id: String,
    pub kinematics: String,
    pub software: String,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub enum MachineStateKind {
    Off,
    Idle,
    Cutting,
    Measuring,
    Alarm,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct StateMsg {
    pub state: MachineStateKind,
    pub program: Option<String>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct SpindleMsg {
    pub rpm: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct TemperatureMsg {
    pub sensor: String,
    pub celsius: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct DisplacementMsg {
    pub sensor: String,
    pub um: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum DetectionStatus {
    Ok,
    NoTrip,
    Aborted,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct DetectionMsg {
    pub cycle: i64,
    pub step: String,
    pub b_deg: f64,
    pub c_deg: f64,
    pub axis: Axis,
    pub direction: i8,
    pub feed_mm_min: f64,
    pub spindle_rpm: f64,
    pub tool_id: String,
    pub x_mm: f64,
    pub y_mm: f64,
    pub z_mm: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub status: Option<DetectionStatus>,
}

impl DetectionMsg {
    pub fn status(&self) -> DetectionStatus {
        self.status.unwrap_or(DetectionStatus::Ok)
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum ResultStatus {
    Ok,
    Rejected,
}

/// `/cycle/result`. `errors` and `sigma` are null when a rejected cycle has no solution. The
/// fields after `residual_rms_um` are this project's additions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct CycleResultMsg {
    pub cycle: i64,
    pub t_ns: i64,
    pub status: ResultStatus,
    pub reason: Option<String>,
    pub errors: Option<BTreeMap<String, f64>>,
    pub sigma: Option<BTreeMap<String, f64>>,
    pub residual_rms_um: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub chi2: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dof: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub n_detections: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nuisance: Option<BTreeMap<String, f64>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub redundancy_um: Option<Vec<f64>>,
    /// The chi-square point the validation compared `chi2` with (at its configured
    /// probability, for `dof`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub chi2_point: Option<f64>,
    /// What was set aside without rejecting the cycle (a retried approach, a duplicate).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub notes: Option<Vec<String>>,
    /// The linear-axis geometry the solve started from (a stored geometry version, or the
    /// machine file's); absent when the axes were taken as perfect.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub geometry: Option<String>,
}

/// A message with its log time (ns since the Unix epoch).
#[derive(Debug, Clone, PartialEq)]
pub struct Timed<T> {
    pub t_ns: i64,
    pub msg: T,
}

/// Why a `/probe/detection` message could not be taken, with what could still be read of it.
#[derive(Debug, Clone, PartialEq)]
pub struct DetectionIssue {
    pub cycle: Option<i64>,
    pub step: Option<String>,
    pub message: String,
}

/// A message as written: its topic, log time and JSON bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct RawMessage {
    pub topic: String,
    pub t_ns: i64,
    pub data: Vec<u8>,
}

/// Everything a reader takes from one recording, per topic, each in log-time order.
#[derive(Debug, Clone, Default)]
pub struct Recording {
    pub info: Option<MachineInfo>,
    pub states: Vec<Timed<StateMsg>>,
    pub spindle: Vec<Timed<SpindleMsg>>,
    pub temperatures: Vec<Timed<TemperatureMsg>>,
    pub displacements: Vec<Timed<DisplacementMsg>>,
    pub detections: Vec<Timed<Result<DetectionMsg, DetectionIssue>>>,
    pub results: Vec<Timed<CycleResultMsg>>,
    /// Message counts of topics the reader does not interpret.
    pub other_topics: BTreeMap<String, u64>,
    /// Messages of known topics (other than detections) that were skipped, and why.
    pub problems: Vec<String>,
    /// Set when the file ended early and only its complete chunks were read.
    pub truncated: Option<String>,
    /// Every message in file order, when asked for (`ReadOptions::keep_raw`).
    pub raw: Vec<RawMessage>,
}

/// The fields every `/probe/detection` message must have.
pub const DETECTION_FIELDS: [&str; 12] = [
    "cycle",
    "step",
    "b_deg",
    "c_deg",
    "axis",
    "direction",
    "feed_mm_min",
    "spindle_rpm",
    "tool_id",
    "x_mm",
    "y_mm",
    "z_mm",
];

/// Parse a `/probe/detection` payload. Non-finite numbers (`NaN`, `Infinity`, as some JSON
/// writers emit them), missing fields and wrong types are reported by field name.
pub fn parse_detection(data: &[u8]) -> Result<DetectionMsg, DetectionIssue> {
    let issue = |cycle, step, message: String| DetectionIssue {
        cycle,
        step,
        message,
    };
    let text = std::str::from_utf8(data)
        .map_err(|_| issue(None, None, "payload is not UTF-8 text".into()))?;
    let (value, nonfinite) = match serde_json::from_str::<Value>(text) {
        Ok(v) => (v, false),
        Err(first) => {
            let cleaned = replace_nonfinite_tokens(text);
            match serde_json::from_str::<Value>(&cleaned) {
                Ok(v) if cleaned != text => (v, true),
                _ => return Err(issue(None, None, format!("not valid JSON: {first}"))),
            }
        }
    };
    let Value::Object(map) = &value else {
        return Err(issue(None, None, "payload is not a JSON object".into()));
    };
    let cycle = map.get("cycle").and_then(Value::as_i64);
    let step = map.get("step").and_then(Value::as_str).map(str::to_string);
    let fail = |m: String| issue(cycle, step.clone(), m);
    for key in DETECTION_FIELDS {
        match map.get(key) {
            None => return Err(fail(format!("field '{key}' is missing"))),
            Some(Value::Null) if nonfinite => {
                return Err(fail(format!(
                    "field '{key}' is not a finite number (NaN or Infinity)"
                )));
            }
            Some(Value::Null) => return Err(fail(format!("field '{key}' is null"))),
            _ => {}
        }
    }
    let msg: DetectionMsg = serde_json::from_value(value.clone())
        .map_err(|e| fail(format!("field types do not match the contract: {e}")))?;
    if msg.direction != 1 && msg.direction != -1 {
        return Err(fail(format!(
            "direction must be -1 or 1, not {}",
            msg.direction
        )));
    }
    Ok(msg)
}

/// Replace bare `NaN`, `Infinity` and `-Infinity` tokens outside strings by `null`.
fn replace_nonfinite_tokens(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut in_string = false;
    let mut escaped = false;
    let chars: Vec<char> = text.chars().collect();
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        if in_string {
            out.push(c);
            if escaped {
                escaped = false;
            } else if c == '\\' {
                escaped = true;
            } else if c == '"' {
                in_string = false;
            }
            i += 1;
            continue;
        }
        if c == '"' {
            in_string = true;
            out.push(c);
            i += 1;
            continue;
        }
        let rest: String = chars[i..chars.len().min(i + 9)].iter().collect();
        let token = ["-Infinity", "Infinity", "NaN"]
            .into_iter()
            .find(|t| rest.starts_with(t));
        if let Some(t) = token {
            out.push_str("null");
            i += t.len();
        } else {
            out.push(c);
            i += 1;
        }
    }
    out
}

/// JSON Schema (draft 2020-12) of a contract topic, or a permissive object schema for any
/// other topic.
pub fn schema(topic: &str) -> (String, Value) {
    let num = json!({"type": "number"});
    let s = |name: &str, props: Value, required: &[&str]| {
        (
            name.to_string(),
            json!({
                "$schema": "https://json-schema.org/draft/2020-12/schema",
                "title": name,
                "type": "object",
                "properties": props,
                "required": required,
            }),
        )
    };
    match topic {
        TOPIC_INFO => s(
            "driftwatch.MachineInfo",
            json!({"machine_id": {"type": "string"}, "kinematics": {"type": "string"}, "software": {"type": "string"}}),
            &["machine_id", "kinematics", "software"],
        ),
        TOPIC_STATE => s(
            "driftwatch.MachineState",
            json!({"state": {"enum": ["off", "idle", "cutting", "measuring", "alarm"]},
                   "program": {"type": ["string", "null"]}}),
            &["state"],
        ),
        TOPIC_SPINDLE => s("driftwatch.Spindle", json!({"rpm": num}), &["rpm"]),
        TOPIC_TEMPERATURE => s(
            "driftwatch.Temperature",
            json!({"sensor": {"type": "string"}, "celsius": num}),
            &["sensor", "celsius"],
        ),
        TOPIC_DISPLACEMENT => s(
            "driftwatch.Displacement",
            json!({"sensor": {"type": "string"}, "um": num}),
            &["sensor", "um"],
        ),
        TOPIC_DETECTION => s(
            "driftwatch.ProbeDetection",
            json!({
                "cycle": {"type": "integer"}, "step": {"type": "string"},
                "b_deg": num, "c_deg": num,
                "axis": {"enum": ["x", "y", "z"]}, "direction": {"enum": [-1, 1]},
                "feed_mm_min": num, "spindle_rpm": num, "tool_id": {"type": "string"},
                "x_mm": num, "y_mm": num, "z_mm": num,
                "status": {"enum": ["ok", "no_trip", "aborted"]}
            }),
            &DETECTION_FIELDS,
        ),
        TOPIC_RESULT => {
            let map =
                json!({"type": ["object", "null"], "additionalProperties": {"type": "number"}});
            s(
                "driftwatch.CycleResult",
                json!({
                    "cycle": {"type": "integer"}, "t_ns": {"type": "integer"},
                    "status": {"enum": ["ok", "rejected"]}, "reason": {"type": ["string", "null"]},
                    "errors": map, "sigma": map, "residual_rms_um": {"type": ["number", "null"]},
                    "chi2": num, "dof": {"type": "integer"}, "n_detections": {"type": "integer"},
                    "nuisance": {"type": "object", "additionalProperties": num},
                    "redundancy_um": {"type": "array", "items": num},
                    "chi2_point": num,
                    "notes": {"type": "array", "items": {"type": "string"}},
                    "geometry": {"type": "string"}
                }),
                &[
                    "cycle",
                    "t_ns",
                    "status",
                    "reason",
                    "errors",
                    "sigma",
                    "residual_rms_um",
                ],
            )
        }
        TOPIC_RTEST_SETUP => {
            let row = json!({"type": "array", "items": num, "minItems": 3, "maxItems": 3});
            let m3 = json!({"type": "array", "items": row, "minItems": 3, "maxItems": 3});
            s(
                "driftwatch.RtestSetup",
                json!({"run": {"type": "integer"}, "test": {"enum": ["BK1", "BK2", "XYC"]},
                       "setting": {"enum": ["E", "J", "Es"]}, "axis": {"type": "string"},
                       "ball_mm": row, "sensitivity": m3, "sensitivity_source": {"type": "string"},
                       "sensitivity_row_cov": m3, "reading_sigma_um": num, "sphericity_um": num}),
                &[
                    "run",
                    "test",
                    "setting",
                    "axis",
                    "ball_mm",
                    "sensitivity",
                    "sensitivity_source",
                    "reading_sigma_um",
                ],
            )
        }
        TOPIC_RTEST_READING => s(
            "driftwatch.RtestReading",
            json!({"run": {"type": "integer"}, "index": {"type": "integer", "minimum": 0},
                   "b_deg": num, "c_deg": num, "x_mm": num, "y_mm": num, "z_mm": num,
                   "u_um": num, "v_um": num, "w_um": num}),
            &[
                "run", "index", "b_deg", "c_deg", "x_mm", "y_mm", "z_mm", "u_um", "v_um", "w_um",
            ],
        ),
        _ => (
            format!("driftwatch{}", topic.replace('/', ".")),
            json!({"$schema": "https://json-schema.org/draft/2020-12/schema", "type": "object"}),
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn good() -> Value {
        json!({"cycle": 3, "step": "B0C0/z", "b_deg": 0.0, "c_deg": 0.0, "axis": "z",
               "direction": -1, "feed_mm_min": 100.0, "spindle_rpm": 20000.0, "tool_id": "EM10",
               "x_mm": 0.0, "y_mm": -100.0, "z_mm": 70.001, "extra_field": 1})
    }

    #[test]
    fn parses_a_contract_detection_and_ignores_unknown_fields() {
        let m = parse_detection(good().to_string().as_bytes()).unwrap();
        assert_eq!(m.cycle, 3);
        assert_eq!(m.status(), DetectionStatus::Ok);
        assert_eq!(m.axis, Axis::Z);
    }

    #[test]
    fn names_non_finite_and_missing_fields() {
        let text = good().to_string().replace("70.001", "NaN");
        let e = parse_detection(text.as_bytes()).unwrap_err();
        assert_eq!(e.cycle, Some(3));
        assert!(
            e.message.contains("z_mm") && e.message.contains("NaN"),
            "{}",
            e.message
        );
        let mut v = good();
        v.as_object_mut().unwrap().remove("feed_mm_min");
        let e = parse_detection(v.to_string().as_bytes()).unwrap_err();
        assert!(e.message.contains("feed_mm_min"), "{}", e.message);
        let e = parse_detection(b"{not json").unwrap_err();
        assert!(e.message.contains("not valid JSON"));
    }

    /// The schema a recording publishes for each contract topic (hand-written, as the
    /// contract spells it) agrees with the struct the topic's messages are read into (its
    /// schema derived by schemars): the same properties, every field the struct needs required,
    /// and the same values for each enumerated field.
    #[test]
    fn each_published_schema_agrees_with_its_struct() {
        fn derived<T: JsonSchema>() -> Value {
            serde_json::to_value(schemars::schema_for!(T)).unwrap()
        }
        fn keys(v: &Value) -> std::collections::BTreeSet<String> {
            v.as_object()
                .into_iter()
                .flatten()
                .map(|(k, _)| k.clone())
                .collect()
        }
        fn strings(v: &Value) -> std::collections::BTreeSet<String> {
            v.as_array()
                .into_iter()
                .flatten()
                .map(|x| x.to_string())
                .collect()
        }
        // The enumerated values a derived property allows, following its $ref, also inside
        // the `anyOf` with null that schemars writes for an Option.
        fn enum_of(d: &Value, prop: &Value) -> Option<std::collections::BTreeSet<String>> {
            let alternatives =
                std::iter::once(prop).chain(prop["anyOf"].as_array().into_iter().flatten());
            let mut out = std::collections::BTreeSet::new();
            for alt in alternatives {
                let target = match alt["$ref"].as_str() {
                    Some(r) => d.pointer(r.trim_start_matches('#'))?,
                    None => alt,
                };
                out.extend(strings(&target["enum"]));
            }
            (!out.is_empty()).then_some(out)
        }
        let topics = [
            (TOPIC_INFO, derived::<MachineInfo>()),
            (TOPIC_STATE, derived::<StateMsg>()),
            (TOPIC_SPINDLE, derived::<SpindleMsg>()),
            (TOPIC_TEMPERATURE, derived::<TemperatureMsg>()),
            (TOPIC_DISPLACEMENT, derived::<DisplacementMsg>()),
            (TOPIC_DETECTION, derived::<DetectionMsg>()),
            (TOPIC_RESULT, derived::<CycleResultMsg>()),
        ];
        for (topic, d) in topics {
            let (_, published) = schema(topic);
            assert_eq!(
                keys(&published["properties"]),
                keys(&d["properties"]),
                "{topic}: the published properties differ from the struct's"
            );
            let required = strings(&published["required"]);
            for field in strings(&d["required"]) {
                assert!(
                    required.contains(&field),
                    "{topic}: the struct needs {field}, the published schema does not require it"
                );
            }
            for (name, p) in d["properties"].as_object().unwrap() {
                if let Some(values) = enum_of(&d, p) {
                    assert_eq!(
                        strings(&published["properties"][name]["enum"]),
                        values,
                        "{topic}.{name}: the published values differ from the struct's"
                    );
                }
            }
        }
    }

    #[test]
    fn nan_inside_strings_is_left_alone() {
        let mut v = good();
        v["step"] = json!("NaN-Infinity step");
        let m = parse_detection(v.to_string().as_bytes()).unwrap();
        assert_eq!(m.step, "NaN-Infinity step");
    }
}
