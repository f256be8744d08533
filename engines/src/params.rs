//! Engine parameter schemas: what an engine accepts, with ranges, so that a bad value from the
//! control socket is refused with a message instead of reaching the GPU.

use serde::Serialize;
use serde_json::{Map, Value};

#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ParamKind {
    Float {
        min: f64,
        max: f64,
        default: f64,
    },
    Int {
        min: i64,
        max: i64,
        default: i64,
    },
    Bool {
        default: bool,
    },
    Choice {
        options: Vec<&'static str>,
        default: &'static str,
    },
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ParamSpec {
    pub name: &'static str,
    pub doc: &'static str,
    #[serde(flatten)]
    pub kind: ParamKind,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ParamError {
    #[error("unknown parameter `{name}`; known: {known}")]
    Unknown { name: String, known: String },
    #[error("parameter `{name}`: expected {expected}, got {got}")]
    WrongType {
        name: String,
        expected: &'static str,
        got: String,
    },
    #[error("parameter `{name}`: {value} is outside [{min}, {max}]")]
    OutOfRange {
        name: String,
        value: String,
        min: String,
        max: String,
    },
    #[error("parameter `{name}`: `{value}` is not one of {options}")]
    NotAChoice {
        name: String,
        value: String,
        options: String,
    },
}

impl ParamError {
    /// The parameter the error is about, as the request or the file wrote it.
    pub fn name(&self) -> &str {
        match self {
            ParamError::Unknown { name, .. }
            | ParamError::WrongType { name, .. }
            | ParamError::OutOfRange { name, .. }
            | ParamError::NotAChoice { name, .. } => name,
        }
    }
}

/// `name=value` as the command lines write a parameter (`relightd --param`, `relightctl`, a
/// bench setting): the value as JSON where it parses (a number, a bool, a quoted string), else
/// as the plain string. `None` without an `=`.
pub fn parse_assignment(text: &str) -> Option<(&str, Value)> {
    let (name, value) = text.split_once('=')?;
    let value = serde_json::from_str(value).unwrap_or_else(|_| Value::from(value));
    Some((name, value))
}

/// The parameters one engine accepts.
#[derive(Debug, Clone, PartialEq, Default, Serialize)]
pub struct ParamsSchema {
    pub params: Vec<ParamSpec>,
}

impl ParamsSchema {
    pub fn new(params: Vec<ParamSpec>) -> Self {
        Self { params }
    }

    /// Every parameter at its default value.
    pub fn defaults(&self) -> Map<String, Value> {
        self.params
            .iter()
            .map(|p| {
                let value = match &p.kind {
                    ParamKind::Float { default, .. } => Value::from(*default),
                    ParamKind::Int { default, .. } => Value::from(*default),
                    ParamKind::Bool { default } => Value::from(*default),
                    ParamKind::Choice { default, .. } => Value::from(*default),
                };
                (p.name.to_owned(), value)
            })
            .collect()
    }

    /// Whether the engine takes a parameter `name`.
    pub fn has(&self, name: &str) -> bool {
        self.params.iter().any(|p| p.name == name)
    }

    fn spec(&self, name: &str) -> &ParamSpec {
        self.params
            .iter()
            .find(|p| p.name == name)
            .unwrap_or_else(|| panic!("the engine reads `{name}`, which its schema lacks"))
    }

    /// Integer parameter `name` from `params` (as [`validate`](Self::validate) returns them),
    /// else its default; within the spec's range either way, so an engine's settings take
    /// their default and bounds from one place.
    pub fn int(&self, params: &Map<String, Value>, name: &str) -> i64 {
        match self.spec(name).kind {
            ParamKind::Int { min, max, default } => params
                .get(name)
                .and_then(Value::as_i64)
                .unwrap_or(default)
                .clamp(min, max),
            _ => panic!("parameter `{name}` is not an integer"),
        }
    }

    /// Float parameter `name`, as [`int`](Self::int).
    pub fn float(&self, params: &Map<String, Value>, name: &str) -> f64 {
        match self.spec(name).kind {
            ParamKind::Float { min, max, default } => params
                .get(name)
                .and_then(Value::as_f64)
                .filter(|v| v.is_finite())
                .unwrap_or(default)
                .clamp(min, max),
            _ => panic!("parameter `{name}` is not a number"),
        }
    }

    /// Choice parameter `name`: one of its options, else its default.
    pub fn choice<'a>(&'a self, params: &'a Map<String, Value>, name: &str) -> &'a str {
        match &self.spec(name).kind {
            ParamKind::Choice { options, default } => params
                .get(name)
                .and_then(Value::as_str)
                .filter(|v| options.contains(v))
                .unwrap_or(default),
            _ => panic!("parameter `{name}` is not a choice"),
        }
    }

    /// Check `update` against the schema and return `current` with the update applied.
    /// Nothing is applied unless every entry is valid.
    pub fn validate(
        &self,
        current: &Map<String, Value>,
        update: &Map<String, Value>,
    ) -> Result<Map<String, Value>, ParamError> {
        let mut merged = current.clone();
        for (name, value) in update {
            let spec =
                self.params
                    .iter()
                    .find(|p| p.name == name)
                    .ok_or_else(|| ParamError::Unknown {
                        name: name.clone(),
                        known: self.known_names(),
                    })?;
            merged.insert(name.clone(), spec.check(value)?);
        }
        Ok(merged)
    }

    fn known_names(&self) -> String {
        if self.params.is_empty() {
            return "(none)".to_owned();
        }
        self.params
            .iter()
            .map(|p| p.name)
            .collect::<Vec<_>>()
            .join(", ")
    }
}

impl ParamSpec {
    pub fn int(name: &'static str, doc: &'static str, min: i64, max: i64, default: i64) -> Self {
        Self {
            name,
            doc,
            kind: ParamKind::Int { min, max, default },
        }
    }

    /// A float parameter (defaults given as f32, the precision engines keep them in).
    pub fn float(name: &'static str, doc: &'static str, min: f64, max: f64, default: f32) -> Self {
        Self {
            name,
            doc,
            kind: ParamKind::Float {
                min,
                max,
                default: f64::from(default),
            },
        }
    }

    /// A choice among `options`; the first is the default.
    pub fn choice(name: &'static str, doc: &'static str, options: Vec<&'static str>) -> Self {
        let default = options[0];
        Self {
            name,
            doc,
            kind: ParamKind::Choice { options, default },
        }
    }

    fn check(&self, value: &Value) -> Result<Value, ParamError> {
        let wrong_type = |expected| ParamError::WrongType {
            name: self.name.to_owned(),
            expected,
            got: value.to_string(),
        };
        let out_of_range = |min: &dyn ToString, max: &dyn ToString| ParamError::OutOfRange {
            name: self.name.to_owned(),
            value: value.to_string(),
            min: min.to_string(),
            max: max.to_string(),
        };
        match &self.kind {
            ParamKind::Float { min, max, .. } => {
                let v = value.as_f64().ok_or_else(|| wrong_type("a number"))?;
                if !(v.is_finite() && (*min..=*max).contains(&v)) {
                    return Err(out_of_range(min, max));
                }
                Ok(Value::from(v))
            }
            ParamKind::Int { min, max, .. } => {
                let v = value.as_i64().ok_or_else(|| wrong_type("an integer"))?;
                if !(*min..=*max).contains(&v) {
                    return Err(out_of_range(min, max));
                }
                Ok(Value::from(v))
            }
            ParamKind::Bool { .. } => value
                .as_bool()
                .map(Value::from)
                .ok_or_else(|| wrong_type("true or false")),
            ParamKind::Choice { options, .. } => {
                let v = value.as_str().ok_or_else(|| wrong_type("a string"))?;
                if options.contains(&v) {
                    Ok(Value::from(v))
                } else {
                    Err(ParamError::NotAChoice {
                        name: self.name.to_owned(),
                        value: v.to_owned(),
                        options: options.join(", "),
                    })
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn an_assignment_takes_json_where_it_parses_and_the_text_else() {
        assert_eq!(parse_assignment("steps=16"), Some(("steps", json!(16))));
        assert_eq!(parse_assignment("step=0.5"), Some(("step", json!(0.5))));
        assert_eq!(
            parse_assignment("shadows=cones"),
            Some(("shadows", json!("cones")))
        );
        assert_eq!(parse_assignment("a=b=c"), Some(("a", json!("b=c"))));
        assert_eq!(parse_assignment("steps"), None);
    }

    fn schema() -> ParamsSchema {
        ParamsSchema::new(vec![
            ParamSpec {
                name: "steps",
                doc: "propagation steps",
                kind: ParamKind::Int {
                    min: 1,
                    max: 64,
                    default: 32,
                },
            },
            ParamSpec {
                name: "mode",
                doc: "",
                kind: ParamKind::Choice {
                    options: vec!["a", "b"],
                    default: "a",
                },
            },
        ])
    }

    /// Settings read back take the spec's default when absent and stay within its range.
    #[test]
    fn readers_take_default_and_range_from_the_spec() {
        let schema = schema();
        let none = Map::new();
        assert_eq!(schema.int(&none, "steps"), 32);
        assert_eq!(schema.choice(&none, "mode"), "a");
        let given = json!({ "steps": 500, "mode": "b" });
        let given = given.as_object().unwrap();
        assert_eq!(schema.int(given, "steps"), 64);
        assert_eq!(schema.choice(given, "mode"), "b");
        let odd = json!({ "mode": "c" });
        assert_eq!(schema.choice(odd.as_object().unwrap(), "mode"), "a");
    }

    fn map(v: Value) -> Map<String, Value> {
        v.as_object().cloned().unwrap()
    }

    #[test]
    fn valid_update_is_merged_over_defaults() {
        let s = schema();
        let merged = s
            .validate(&s.defaults(), &map(json!({"steps": 8})))
            .unwrap();
        assert_eq!(Value::Object(merged), json!({"steps": 8, "mode": "a"}));
    }

    #[test]
    fn each_bad_value_names_the_parameter() {
        let s = schema();
        let d = s.defaults();
        for (update, needle) in [
            (json!({"steps": 0}), "outside [1, 64]"),
            (json!({"steps": "many"}), "expected an integer"),
            (json!({"mode": "c"}), "not one of a, b"),
            (json!({"nope": 1}), "known: steps, mode"),
        ] {
            let err = s.validate(&d, &map(update)).unwrap_err().to_string();
            assert!(err.contains(needle), "{err}");
        }
    }

    #[test]
    fn nothing_is_applied_when_one_entry_is_bad() {
        let s = schema();
        let d = s.defaults();
        assert!(
            s.validate(&d, &map(json!({"steps": 4, "mode": "zzz"})))
                .is_err()
        );
        assert_eq!(d, s.defaults());
    }
}
