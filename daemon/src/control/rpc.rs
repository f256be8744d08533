//! JSON-RPC 2.0 request handling, independent of the transport: one request line in, at most one
//! response line out (<https://www.jsonrpc.org/specification>).
//!
//! Methods and their params (by name, or by position in the order listed):
//!
//! | method              | params                         | result                         |
//! |---------------------|--------------------------------|--------------------------------|
//! | `status`            | —                              | [`StatusReport`]               |
//! | `engine.list`       | —                              | `[`[`EngineInfo`]`]`           |
//! | `engine.set`        | `name`                         | `null`                         |
//! | `engine.params.get` | —                              | the parameter object           |
//! | `engine.params.set` | `params` (object), see below   | the full new parameter object  |
//! | `record.start`      | `path`?, `overwrite`?          | `{"path": ...}`                |
//! | `record.stop`       | —                              | the recording summary          |
//! | `snapshot`          | `path`?, `overwrite`?          | `{"paths": [...]}`             |
//! | `config.reload`     | —                              | what changed                   |
//! | `replay.step`       | `frames`? (integer ≥ 1, def. 1)| `{"frames": n}`                |
//! | `rpc.ping`          | —                              | `"pong"`                       |
//! | `version`           | —                              | `{"name", "version", "protocol"}` |
//! | `lights.get`        | —                              | [`LightingEstimate`] or `null` |
//! | `lights.export`     | `{path, overwrite?}`           | `{path, width, height}`: the HDR environment as EXR |
//! | `lights.subscribe`  | —                              | `null`, then notifications     |
//! | `lights.unsubscribe`| —                              | `null`                         |
//!
//! After `lights.subscribe` the server sends, on that connection, a notification
//! `{"jsonrpc": "2.0", "method": "lights.update", "params": <LightingEstimate>}` each time the
//! estimate changes, the first one right after the `lights.subscribe` response (when there is an
//! estimate already). `lights.get` is `null` until the pipeline publishes its first estimate
//! (with a `[scene]`, from the first frame set it renders). Subscribing twice is harmless; after
//! the `lights.unsubscribe` response no more updates come. A subscribed connection is not closed
//! for being idle. Updates are coalesced to the newest for a subscriber that reads slowly, and
//! one that stops reading is disconnected (see [`super::lights`] and [`super::server`]); either
//! way the pipeline and the other connections never wait for it. Subscriptions need a
//! connection: [`handle_line`] (no transport) answers `lights.subscribe` with an error.
//!
//! `engine.params.set` accepts `{"params": {...}}`, `[{...}]`, or the parameter object itself
//! (`{"exposure": 2.0}`); an object whose only key is `params` is always read as the wrapped form.
//! Optional params may be `null`. Blank lines are ignored.
//!
//! Output paths (`record.start`, `snapshot`): a relative path is taken from the recorder's or the
//! snapshot directory, not from the daemon's working directory; `..` and control characters
//! are refused (−32602); an existing file is refused unless `overwrite` is `true`; a file that
//! cannot be created is −32003 (`data.path` names it). Ids are echoed exactly as sent, digit for
//! digit (`18446744073709551616` stays that, `1.0` stays `1.0`).

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::PathBuf;

use serde::Serialize;
use serde_json::{Map, Value, json};

use super::lights::LightsSubscription;
use super::types::{ControlError, ControlTarget, OutputRequest};
#[cfg(doc)]
use super::types::{EngineInfo, StatusReport};
#[cfg(doc)]
use relight_recon::estimate::LightingEstimate;

/// The method of the notifications a `lights.subscribe` connection receives.
pub const LIGHTS_UPDATE: &str = "lights.update";

/// Every method the server answers, for `method not found` hints.
pub const METHODS: [&str; 16] = [
    "status",
    "engine.list",
    "engine.set",
    "engine.params.get",
    "engine.params.set",
    "record.start",
    "record.stop",
    "snapshot",
    "config.reload",
    "replay.step",
    "rpc.ping",
    "version",
    "lights.get",
    "lights.export",
    "lights.subscribe",
    "lights.unsubscribe",
];

/// The connection a request arrived on, for methods whose effect outlives the request.
pub trait Session {
    /// Whether `lights.update` notifications are being sent on this connection.
    fn lights_subscribed(&self) -> bool;
    /// Sends `lights.update` notifications from `subscription`, starting after the response to
    /// the current request (line) has been written.
    fn subscribe_lights(&mut self, subscription: LightsSubscription) -> Result<(), ControlError>;
    /// Stops the notifications; when this returns, none will be written any more.
    fn unsubscribe_lights(&mut self);
}

/// The session of a caller without a connection ([`handle_line`]): it cannot take notifications.
#[derive(Debug, Clone, Copy, Default)]
pub struct NoSession;

impl Session for NoSession {
    fn lights_subscribed(&self) -> bool {
        false
    }

    fn subscribe_lights(&mut self, subscription: LightsSubscription) -> Result<(), ControlError> {
        subscription.close();
        Err(ControlError::failed(
            "lights.subscribe needs a connection that can receive notifications (the control socket)",
        ))
    }

    fn unsubscribe_lights(&mut self) {}
}

/// The `lights.update` notification line (without newline) for `estimate`.
pub fn lights_update_line<T: Serialize + ?Sized>(
    estimate: &T,
) -> Result<String, serde_json::Error> {
    #[derive(Serialize)]
    struct Notification<'a, T: ?Sized> {
        jsonrpc: &'static str,
        method: &'static str,
        params: &'a T,
    }
    // Serialised directly (not through `Value`), so that f32 fields keep their shortest form.
    serde_json::to_string(&Notification {
        jsonrpc: "2.0",
        method: LIGHTS_UPDATE,
        params: estimate,
    })
}

/// Handles one request line (without its newline). Returns the response line (without newline),
/// or `None` when nothing must be sent back (notifications, blank lines). Without a connection:
/// `lights.subscribe` is an error (see [`handle_line_in`]).
pub fn handle_line(line: &[u8], target: &dyn ControlTarget) -> Option<String> {
    handle_line_in(line, target, &mut NoSession)
}

/// [`handle_line`] for a request that arrived on a connection, `session`.
pub fn handle_line_in(
    line: &[u8],
    target: &dyn ControlTarget,
    session: &mut dyn Session,
) -> Option<String> {
    handle_line_capped(line, target, session, usize::MAX)
}

/// [`handle_line_in`] with a batch's reply capped at `max_reply_bytes`: a batch whose replies
/// grow past it stops there and is answered with one error naming the limit.
pub fn handle_line_capped(
    line: &[u8],
    target: &dyn ControlTarget,
    session: &mut dyn Session,
    max_reply_bytes: usize,
) -> Option<String> {
    let text = match std::str::from_utf8(line) {
        Ok(text) => text,
        Err(err) => {
            let error = ControlError::parse_error(format!(
                "parse error: invalid UTF-8 at byte {}",
                err.valid_up_to()
            ));
            return Some(error_response(Value::Null, &error).to_string());
        }
    };
    let text = text.trim();
    if text.is_empty() {
        return None;
    }
    let response = match serde_json::from_str::<Value>(text) {
        Ok(value) => handle_value_capped(value, target, session, max_reply_bytes)?,
        Err(err) => error_response(
            Value::Null,
            &ControlError::parse_error(format!("parse error: {err}")),
        ),
    };
    Some(with_ids_as_sent(response, text))
}

/// The `id` member of a request, as written.
#[derive(serde::Deserialize)]
struct RawId<'a> {
    #[serde(borrow, default)]
    id: Option<&'a serde_json::value::RawValue>,
}

/// The numeric ids of the request(s) in `text` as they were written, where parsing into a
/// [`Value`] changed them (a u64 overflow becomes an f64, `1e3` becomes `1000.0`).
fn altered_numeric_ids(text: &str) -> Vec<(Value, &str)> {
    fn raw_id(request: &str) -> Option<&str> {
        let id = serde_json::from_str::<RawId<'_>>(request).ok()?.id?.get();
        id.starts_with(|c: char| c == '-' || c.is_ascii_digit())
            .then_some(id)
    }
    let ids: Vec<&str> = match serde_json::from_str::<Vec<&serde_json::value::RawValue>>(text) {
        Ok(batch) => batch.iter().filter_map(|r| raw_id(r.get())).collect(),
        Err(_) => raw_id(text).into_iter().collect(),
    };
    ids.into_iter()
        .filter_map(|raw| {
            let parsed: Value = serde_json::from_str(raw).ok()?;
            let written = serde_json::to_string(&parsed).ok()?;
            (written != raw).then_some((parsed, raw))
        })
        .collect()
}

/// The response line, with each numeric id written as its request wrote it: the id is the
/// client's to match responses by, digit for digit.
fn with_ids_as_sent(response: Value, text: &str) -> String {
    let mut altered = altered_numeric_ids(text);
    if altered.is_empty() {
        return response.to_string();
    }
    let mut write_one = |response: &Value| -> String {
        let Some(position) = response
            .get("id")
            .and_then(|id| altered.iter().position(|(parsed, _)| parsed == id))
        else {
            return response.to_string();
        };
        let (_, raw) = altered.remove(position);
        let mut without_id = response.clone();
        if let Some(object) = without_id.as_object_mut() {
            object.remove("id");
        }
        let body = without_id.to_string();
        match body.strip_suffix('}') {
            Some("{") => format!("{{\"id\":{raw}}}"),
            Some(open) => format!("{open},\"id\":{raw}}}"),
            None => body,
        }
    };
    match &response {
        Value::Array(batch) => {
            let parts: Vec<String> = batch.iter().map(&mut write_one).collect();
            format!("[{}]", parts.join(","))
        }
        single => write_one(single),
    }
}

/// Handles one parsed request or batch; `None` when no response is due.
pub fn handle_value(value: Value, target: &dyn ControlTarget) -> Option<Value> {
    handle_value_in(value, target, &mut NoSession)
}

/// [`handle_value`] for a request that arrived on a connection, `session`.
pub fn handle_value_in(
    value: Value,
    target: &dyn ControlTarget,
    session: &mut dyn Session,
) -> Option<Value> {
    handle_value_capped(value, target, session, usize::MAX)
}

fn handle_value_capped(
    value: Value,
    target: &dyn ControlTarget,
    session: &mut dyn Session,
    max_reply_bytes: usize,
) -> Option<Value> {
    match value {
        Value::Array(batch) if batch.is_empty() => Some(error_response(
            Value::Null,
            &ControlError::invalid_request("invalid request: empty batch"),
        )),
        Value::Array(batch) => {
            let requests = batch.len();
            let mut responses = Vec::new();
            let mut reply_bytes = 2;
            for (answered, request) in batch.into_iter().enumerate() {
                let Some(response) = handle_request(request, target, session) else {
                    continue;
                };
                reply_bytes += encoded_len(&response) + 1;
                if reply_bytes > max_reply_bytes {
                    let error = ControlError::invalid_request(format!(
                        "batch reply over the {max_reply_bytes}-byte limit after {answered} of \
                         {requests} requests; the rest were not run (send fewer per batch)"
                    ))
                    .with_data(json!({
                        "max_reply_bytes": max_reply_bytes,
                        "answered": answered,
                        "requests": requests,
                    }));
                    return Some(error_response(Value::Null, &error));
                }
                responses.push(response);
            }
            (!responses.is_empty()).then_some(Value::Array(responses))
        }
        request => handle_request(request, target, session),
    }
}

/// Bytes of `value` as JSON, counted without building the text.
fn encoded_len(value: &Value) -> usize {
    struct Count(usize);
    impl std::io::Write for Count {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            self.0 += buf.len();
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }
    let mut count = Count(0);
    let _ = serde_json::to_writer(&mut count, value);
    count.0
}

/// A successful response object.
pub fn result_response(id: Value, result: Value) -> Value {
    json!({ "jsonrpc": "2.0", "result": result, "id": id })
}

/// An error response object.
pub fn error_response(id: Value, error: &ControlError) -> Value {
    let mut object = Map::new();
    object.insert("code".to_owned(), Value::from(error.code));
    object.insert("message".to_owned(), Value::from(error.message.clone()));
    if let Some(data) = &error.data {
        object.insert("data".to_owned(), data.clone());
    }
    json!({ "jsonrpc": "2.0", "error": Value::Object(object), "id": id })
}

fn handle_request(
    request: Value,
    target: &dyn ControlTarget,
    session: &mut dyn Session,
) -> Option<Value> {
    let Value::Object(mut request) = request else {
        let error = ControlError::invalid_request(format!(
            "invalid request: expected a JSON object, got {}",
            type_name(&request)
        ));
        return Some(error_response(Value::Null, &error));
    };
    let id = request.remove("id");
    let reply_id = match &id {
        None => Value::Null,
        Some(id @ (Value::String(_) | Value::Number(_) | Value::Null)) => id.clone(),
        Some(other) => {
            let error = ControlError::invalid_request(format!(
                "invalid request: `id` must be a string, a number or null, got {}",
                type_name(other)
            ));
            return Some(error_response(Value::Null, &error));
        }
    };
    if let Err(error) = check_envelope(&request) {
        return Some(error_response(reply_id, &error));
    }
    let method = match request.remove("method") {
        Some(Value::String(method)) => method,
        _ => {
            return Some(error_response(
                reply_id,
                &ControlError::internal("method vanished"),
            ));
        }
    };
    let params = request.remove("params");
    let outcome = catch_unwind(AssertUnwindSafe(|| {
        dispatch(&method, params, target, session)
    }))
    .unwrap_or_else(|_| {
        Err(ControlError::internal(format!(
            "internal error: `{method}` handler panicked"
        )))
    });
    if id.is_none() {
        if let Err(error) = &outcome {
            tracing::debug!(method, %error, "control notification failed");
        }
        return None;
    }
    Some(match outcome {
        Ok(result) => result_response(reply_id, result),
        Err(error) => {
            tracing::debug!(method, %error, "control request failed");
            error_response(reply_id, &error)
        }
    })
}

/// Checks `jsonrpc`, `method` and the shape of `params` (the spec's "invalid request" cases).
fn check_envelope(request: &Map<String, Value>) -> Result<(), ControlError> {
    match request.get("jsonrpc") {
        Some(Value::String(v)) if v == "2.0" => {}
        Some(other) => {
            return Err(ControlError::invalid_request(format!(
                "invalid request: `jsonrpc` must be \"2.0\", got {other}"
            )));
        }
        None => {
            return Err(ControlError::invalid_request(
                "invalid request: missing `jsonrpc`: \"2.0\"",
            ));
        }
    }
    match request.get("method") {
        Some(Value::String(_)) => {}
        Some(other) => {
            return Err(ControlError::invalid_request(format!(
                "invalid request: `method` must be a string, got {}",
                type_name(other)
            )));
        }
        None => {
            return Err(ControlError::invalid_request(
                "invalid request: missing `method`",
            ));
        }
    }
    match request.get("params") {
        None | Some(Value::Object(_) | Value::Array(_)) => Ok(()),
        Some(other) => Err(ControlError::invalid_request(format!(
            "invalid request: `params` must be an object or an array, got {}",
            type_name(other)
        ))),
    }
}

fn dispatch(
    method: &str,
    params: Option<Value>,
    target: &dyn ControlTarget,
    session: &mut dyn Session,
) -> Result<Value, ControlError> {
    match method {
        "status" => {
            no_params(method, params)?;
            to_json(&target.status())
        }
        "engine.list" => {
            no_params(method, params)?;
            to_json(&target.engine_list())
        }
        "engine.set" => {
            let [name] = named_params(method, params, ["name"])?;
            let name = required_string(method, "name", name)?;
            target.engine_set(&name)?;
            Ok(Value::Null)
        }
        "engine.params.get" => {
            no_params(method, params)?;
            Ok(target.engine_params_get())
        }
        "engine.params.set" => {
            let params = engine_params(method, params)?;
            target.engine_params_set(params)
        }
        "record.start" => {
            let request = output_request(method, params)?;
            let path = target.record_start(request)?;
            Ok(json!({ "path": path }))
        }
        "record.stop" => {
            no_params(method, params)?;
            target.record_stop()
        }
        "snapshot" => {
            let request = output_request(method, params)?;
            let paths = target.snapshot(request)?;
            Ok(json!({ "paths": paths }))
        }
        "config.reload" => {
            no_params(method, params)?;
            target.config_reload()
        }
        "replay.step" => {
            let [frames] = named_params(method, params, ["frames"])?;
            let frames = match frames {
                None => 1,
                Some(value) => value
                    .as_u64()
                    .and_then(|n| u32::try_from(n).ok())
                    .filter(|&n| n >= 1)
                    .ok_or_else(|| {
                        ControlError::invalid_params(format!(
                            "{method}: `frames` must be an integer from 1 to {}, got {value}",
                            u32::MAX
                        ))
                    })?,
            };
            target.replay_step(frames)
        }
        "rpc.ping" => {
            no_params(method, params)?;
            Ok(Value::from("pong"))
        }
        "version" => {
            no_params(method, params)?;
            Ok(json!({
                "name": "relightd",
                "version": env!("CARGO_PKG_VERSION"),
                "protocol": "jsonrpc-2.0",
            }))
        }
        "lights.get" => {
            no_params(method, params)?;
            match target.lights().and_then(|board| board.latest()) {
                // Through text, so that f32 fields print in their shortest form (0.1, not
                // 0.10000000149011612).
                Some(estimate) => serde_json::to_string(&*estimate)
                    .and_then(|text| serde_json::from_str(&text))
                    .map_err(|err| ControlError::internal(format!("cannot encode result: {err}"))),
                None => Ok(Value::Null),
            }
        }
        "lights.export" => {
            let request = output_request(method, params)?;
            let Some(path) = request.path.as_deref() else {
                return Err(ControlError::invalid_params(format!(
                    "{method}: `path` is required (an .exr file, relative to the snapshot directory)"
                )));
            };
            target.lights_export(path, request.overwrite)
        }
        "lights.subscribe" => {
            no_params(method, params)?;
            let board = target.lights().ok_or_else(|| {
                ControlError::failed("this daemon publishes no lighting estimate")
            })?;
            if !session.lights_subscribed() {
                session.subscribe_lights(board.subscribe())?;
            }
            Ok(Value::Null)
        }
        "lights.unsubscribe" => {
            no_params(method, params)?;
            session.unsubscribe_lights();
            Ok(Value::Null)
        }
        _ => Err(ControlError::method_not_found(method).with_data(json!({ "methods": METHODS }))),
    }
}

fn to_json<T: Serialize>(value: &T) -> Result<Value, ControlError> {
    serde_json::to_value(value)
        .map_err(|err| ControlError::internal(format!("cannot encode result: {err}")))
}

fn no_params(method: &str, params: Option<Value>) -> Result<(), ControlError> {
    named_params(method, params, []).map(|[]| ())
}

/// Reads params given by name (an object) or by position (an array) into `names`' order; absent
/// and `null` params are `None`. Unknown names and surplus positions are errors.
fn named_params<const N: usize>(
    method: &str,
    params: Option<Value>,
    names: [&str; N],
) -> Result<[Option<Value>; N], ControlError> {
    let mut out: [Option<Value>; N] = std::array::from_fn(|_| None);
    match params {
        None => {}
        Some(Value::Object(mut map)) => {
            if let Some(unknown) = map.keys().find(|k| !names.contains(&k.as_str())) {
                return Err(ControlError::invalid_params(match N {
                    0 => format!("{method} takes no params, got `{unknown}`"),
                    _ => format!(
                        "{method}: unknown param `{unknown}` (expected {})",
                        names.map(|n| format!("`{n}`")).join(", ")
                    ),
                }));
            }
            for (slot, name) in out.iter_mut().zip(names) {
                *slot = map.remove(name).filter(|v| !v.is_null());
            }
        }
        Some(Value::Array(items)) => {
            if items.len() > N {
                return Err(ControlError::invalid_params(format!(
                    "{method} takes at most {N} positional params, got {}",
                    items.len()
                )));
            }
            for (slot, item) in out.iter_mut().zip(items) {
                *slot = Some(item).filter(|v| !v.is_null());
            }
        }
        Some(other) => {
            return Err(ControlError::invalid_params(format!(
                "{method}: params must be an object or an array, got {}",
                type_name(&other)
            )));
        }
    }
    Ok(out)
}

fn required_string(method: &str, name: &str, value: Option<Value>) -> Result<String, ControlError> {
    match value {
        Some(Value::String(s)) => Ok(s),
        Some(other) => Err(ControlError::invalid_params(format!(
            "{method}: `{name}` must be a string, got {}",
            type_name(&other)
        ))),
        None => Err(ControlError::invalid_params(format!(
            "{method}: missing param `{name}`"
        ))),
    }
}

/// `path`? and `overwrite`? of `record.start` and `snapshot`.
fn output_request(method: &str, params: Option<Value>) -> Result<OutputRequest, ControlError> {
    let [path, overwrite] = named_params(method, params, ["path", "overwrite"])?;
    let overwrite = match overwrite {
        None => false,
        Some(Value::Bool(overwrite)) => overwrite,
        Some(other) => {
            return Err(ControlError::invalid_params(format!(
                "{method}: `overwrite` must be true or false, got {}",
                type_name(&other)
            )));
        }
    };
    Ok(OutputRequest {
        path: optional_path(method, "path", path)?,
        overwrite,
    })
}

fn optional_path(
    method: &str,
    name: &str,
    value: Option<Value>,
) -> Result<Option<PathBuf>, ControlError> {
    match value {
        None => Ok(None),
        Some(Value::String(s)) if s.is_empty() => Err(ControlError::invalid_params(format!(
            "{method}: `{name}` must not be empty"
        ))),
        Some(Value::String(s)) if s.chars().any(char::is_control) => {
            Err(ControlError::invalid_params(format!(
                "{method}: `{name}` must not hold control characters, got {s:?}"
            )))
        }
        Some(Value::String(s)) => Ok(Some(PathBuf::from(s))),
        Some(other) => Err(ControlError::invalid_params(format!(
            "{method}: `{name}` must be a string, got {}",
            type_name(&other)
        ))),
    }
}

/// The three accepted shapes of `engine.params.set` params (see the module docs).
fn engine_params(method: &str, params: Option<Value>) -> Result<Map<String, Value>, ControlError> {
    let not_object = |value: &Value| {
        ControlError::invalid_params(format!(
            "{method}: `params` must be an object, got {}",
            type_name(value)
        ))
    };
    match params {
        None => Err(ControlError::invalid_params(format!(
            "{method}: missing param `params`"
        ))),
        Some(Value::Object(mut map)) if map.len() == 1 && map.contains_key("params") => {
            match map.remove("params") {
                Some(Value::Object(inner)) => Ok(inner),
                Some(other) => Err(not_object(&other)),
                None => Ok(Map::new()),
            }
        }
        Some(Value::Object(map)) => Ok(map),
        Some(Value::Array(items)) => {
            let count = items.len();
            let mut items = items.into_iter();
            match (items.next(), count) {
                (Some(Value::Object(inner)), 1) => Ok(inner),
                (Some(other), 1) => Err(not_object(&other)),
                _ => Err(ControlError::invalid_params(format!(
                    "{method} takes exactly 1 positional param (the object), got {count}"
                ))),
            }
        }
        Some(other) => Err(not_object(&other)),
    }
}

fn type_name(value: &Value) -> &'static str {
    match value {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}
