//! The service's configuration: one TOML file (the shipped default, `config/default.toml`,
//! documents every key). Each part is owned by the module it configures.

use std::net::SocketAddr;
use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use driftwatch_machine::alerts::{Rule, default_rules};
use driftwatch_machine::compensation::ValidationLimits;
use driftwatch_machine::phase::PhaseConfig;
use driftwatch_machine::scheduler::SchedulePolicy;

pub const DEFAULT_CONFIG: &str = include_str!("../../../config/default.toml");

#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("cannot read configuration {path}: {source}")]
    Read {
        path: String,
        source: std::io::Error,
    },
    #[error("configuration {origin}: {message}")]
    Parse { origin: String, message: String },
    #[error("configuration {origin}: {message}")]
    Invalid { origin: String, message: String },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    Read,
    Write,
    Admin,
}

impl Role {
    pub fn allows(self, needed: Role) -> bool {
        matches!(
            (self, needed),
            (Role::Admin, _) | (Role::Write, Role::Read | Role::Write) | (Role::Read, Role::Read)
        )
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Token {
    /// Who holds it (for the log; the token itself is never logged).
    pub name: String,
    /// The bearer token, or `env:VAR` to read it from an environment variable.
    pub token: String,
    pub role: Role,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HttpConfig {
    pub listen: SocketAddr,
    /// Whether reads need no token (dashboards and NCs on a trusted network).
    pub anonymous_read: bool,
    #[serde(default)]
    pub tokens: Vec<Token>,
    /// Diagnoses kept per machine: the oldest beyond are deleted as new ones are stored.
    #[serde(default = "default_diagnoses_kept")]
    pub diagnoses_kept: i64,
    /// A request not answered within this is answered 503 `timeout`, s.
    #[serde(default = "default_request_timeout_s")]
    pub request_timeout_s: f64,
    /// Open connections at most; at the cap the oldest connection that has sent no complete
    /// request head is closed for a new one (`crate::http_server`).
    #[serde(default = "default_max_connections")]
    pub max_connections: usize,
    /// A connection that has not sent a complete request head within this is closed, s: from
    /// its accept, or on a kept-alive connection from the first byte of its next request.
    #[serde(default = "default_header_read_timeout_s")]
    pub header_read_timeout_s: f64,
    /// A kept-alive connection whose next request has not begun within this of its last
    /// answer is closed, s.
    #[serde(default = "default_idle_timeout_s")]
    pub idle_timeout_s: f64,
}

impl HttpConfig {
    /// Every `[http]` setting in range.
    pub fn check(&self) -> Result<(), String> {
        if self.diagnoses_kept < 1 {
            return Err(format!(
                "http.diagnoses_kept must be at least 1, not {}",
                self.diagnoses_kept
            ));
        }
        if !(1.0..=3600.0).contains(&self.request_timeout_s) {
            return Err(format!(
                "http.request_timeout_s must be from 1 to 3600 s, not {}",
                self.request_timeout_s
            ));
        }
        if !(1..=1_000_000).contains(&self.max_connections) {
            return Err(format!(
                "http.max_connections must be from 1 to 1000000, not {}",
                self.max_connections
            ));
        }
        if !(0.1..=600.0).contains(&self.header_read_timeout_s) {
            return Err(format!(
                "http.header_read_timeout_s must be from 0.1 to 600 s, not {}",
                self.header_read_timeout_s
            ));
        }
        if !(0.1..=3600.0).contains(&self.idle_timeout_s) {
            return Err(format!(
                "http.idle_timeout_s must be from 0.1 to 3600 s, not {}",
                self.idle_timeout_s
            ));
        }
        Ok(())
    }
}

fn default_diagnoses_kept() -> i64 {
    200
}

fn default_request_timeout_s() -> f64 {
    120.0
}

fn default_max_connections() -> usize {
    512
}

fn default_header_read_timeout_s() -> f64 {
    10.0
}

fn default_idle_timeout_s() -> f64 {
    60.0
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, tag = "kind", rename_all = "snake_case")]
pub enum LinkConfig {
    /// The truth simulator's virtual machine running a scenario's day program.
    Simulated {
        scenario: String,
        /// The scenario's noise seed instead of its own (the machines of a simulated fleet
        /// running one scenario then differ).
        #[serde(default)]
        seed: Option<u64>,
    },
    /// A real NC (or its gateway) posting events and polling for cycle orders over HTTP.
    NcPush {
        /// How far ahead of the service clock an event may be stamped, s.
        #[serde(default = "crate::nc_push::default_max_ahead_s")]
        max_ahead_s: f64,
        /// How far behind it (a gateway's buffer after an outage), s.
        #[serde(default = "crate::nc_push::default_max_behind_s")]
        max_behind_s: f64,
    },
    /// An MTConnect agent's `current` and `sample` streams, followed over HTTP. It observes
    /// only: MTConnect takes no orders, so no cycle is ordered through it.
    Mtconnect {
        /// The agent's base URL, `http://host:5000` (or `https://`).
        agent: String,
        /// The device's name or uuid at the agent (every device of the agent when absent).
        #[serde(default)]
        device: Option<String>,
        /// The data item ids mapped to the recording's topics.
        items: crate::mtconnect::Items,
        /// Wait between two `sample` requests while the agent has nothing more, ms.
        #[serde(default = "default_poll_ms")]
        poll_ms: u64,
        /// Observations asked for per `sample` request.
        #[serde(default = "default_count")]
        count: u32,
        #[serde(default = "crate::nc_push::default_max_ahead_s")]
        max_ahead_s: f64,
        #[serde(default = "crate::nc_push::default_max_behind_s")]
        max_behind_s: f64,
    },
    /// A real NC (or its PLC or gateway) as an OPC UA server (`crate::opcua`).
    Opcua(Box<crate::opcua::OpcuaConfig>),
}

fn default_poll_ms() -> u64 {
    1000
}

fn default_count() -> u32 {
    1000
}

impl LinkConfig {
    /// A real machine (on the wall clock), not the simulator.
    pub fn is_real(&self) -> bool {
        !matches!(self, LinkConfig::Simulated { .. })
    }

    /// The `kind` as configured.
    pub fn kind(&self) -> &'static str {
        match self {
            LinkConfig::Simulated { .. } => "simulated",
            LinkConfig::NcPush { .. } => "nc_push",
            LinkConfig::Mtconnect { .. } => "mtconnect",
            LinkConfig::Opcua(_) => "opcua",
        }
    }

    /// The clock tolerance of a real machine's link (none for the simulator, which is the
    /// clock).
    pub fn clock_tolerance(&self) -> Option<crate::nc_push::ClockTolerance> {
        match self {
            LinkConfig::NcPush {
                max_ahead_s,
                max_behind_s,
            }
            | LinkConfig::Mtconnect {
                max_ahead_s,
                max_behind_s,
                ..
            } => Some(crate::nc_push::ClockTolerance {
                ahead_ns: (max_ahead_s * 1e9) as i64,
                behind_ns: (max_behind_s * 1e9) as i64,
            }),
            LinkConfig::Opcua(c) => Some(c.clock_tolerance()),
            LinkConfig::Simulated { .. } => None,
        }
    }
}

/// An `mtconnect` link's own checks (nothing for the other kinds).
fn validate_mtconnect(link: &LinkConfig) -> Result<(), String> {
    let LinkConfig::Mtconnect {
        agent,
        device,
        items,
        poll_ms,
        count,
        ..
    } = link
    else {
        return Ok(());
    };
    crate::mtconnect_link::endpoint(agent, device.as_deref(), "current")
        .map_err(|e| e.to_string())?;
    if !(50..=600_000).contains(poll_ms) {
        return Err(format!("poll_ms must be from 50 to 600000, not {poll_ms}"));
    }
    if !(1..=100_000).contains(count) {
        return Err(format!("count must be from 1 to 100000, not {count}"));
    }
    let mut ids: Vec<&str> = vec![&items.spindle_speed, &items.execution];
    ids.extend(items.controller_mode.as_deref());
    ids.extend(items.temperatures.values().map(String::as_str));
    if ids.iter().any(|i| i.trim().is_empty()) {
        return Err("an MTConnect data item id is empty".into());
    }
    let mut sorted = ids.clone();
    sorted.sort_unstable();
    if let Some(w) = sorted.windows(2).find(|w| w[0] == w[1]) {
        return Err(format!(
            "data item '{}' is mapped twice: each id maps to one topic",
            w[0]
        ));
    }
    let max = driftwatch_core::kinematics::MAX_NAME_CHARS;
    if let Some(s) = items
        .temperatures
        .keys()
        .find(|s| s.is_empty() || s.chars().count() > max)
    {
        return Err(format!(
            "temperature sensor name '{s}' must have 1 to {max} characters"
        ));
    }
    Ok(())
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MachineConfigEntry {
    pub id: String,
    /// Built-in machine name or path to a machine TOML.
    pub machine: String,
    /// Built-in plan name or path to a plan TOML; default the machine file's `plan`.
    #[serde(default)]
    pub plan: Option<String>,
    pub link: LinkConfig,
    /// A thermal model fitted by `driftwatch fit` (e.g. on an earlier day of this machine):
    /// predictions start from it at once instead of after `thermal.min_cycles` cycles.
    #[serde(default)]
    pub thermal_model: Option<PathBuf>,
    /// This machine's alert rules instead of the service-wide `[[alerts]]` (a machine of
    /// another family has other error names).
    #[serde(default)]
    pub alerts: Option<Vec<Rule>>,
}

impl MachineConfigEntry {
    /// The alert rules this machine runs.
    pub fn alert_rules<'a>(&'a self, service: &'a [Rule]) -> &'a [Rule] {
        self.alerts.as_deref().unwrap_or(service)
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServiceConfig {
    /// Where the database and the recordings go.
    pub data_dir: PathBuf,
    /// The database: absent, the SQLite file `driftwatch.db` in `data_dir`; `postgres://...`,
    /// a PostgreSQL database (the recordings stay in `data_dir`).
    #[serde(default)]
    pub database_url: Option<String>,
    /// Simulated seconds per wall second (1 for real machines).
    pub time_scale: f64,
    /// Largest MCAP file before a new one is started, MiB.
    pub max_file_mib: u64,
    pub http: HttpConfig,
    pub machines: Vec<MachineConfigEntry>,
    #[serde(default)]
    pub phase: PhaseConfig,
    #[serde(default)]
    pub schedule: SchedulePolicy,
    #[serde(default)]
    pub validation: ValidationLimits,
    #[serde(default)]
    pub thermal: driftwatch_machine::compensation::PredictionPolicy,
    #[serde(default = "default_rules")]
    pub alerts: Vec<Rule>,
    /// How a reference instrument's result is compared with the tool setter's.
    #[serde(default)]
    pub verification: driftwatch_machine::verification::VerificationConfig,
    /// Where alert events are POSTed.
    #[serde(default)]
    pub webhooks: Vec<crate::webhook::WebhookConfig>,
    /// Several processes on one PostgreSQL database sharing the machines through leases
    /// (absent: this process runs every configured machine alone).
    #[serde(default)]
    pub fleet: Option<FleetConfig>,
}

/// `[fleet]`: this process's part in a fleet of processes sharing one database.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FleetConfig {
    /// This process's name in the leases; default `<host>-<pid>`.
    #[serde(default)]
    pub process: Option<String>,
    /// A machine whose process has not renewed its lease for this long is taken over by
    /// another, s. Renewed every fifth of it.
    #[serde(default = "default_lease_s")]
    pub lease_s: f64,
    /// Where this process's API answers for the others (requests that change a machine run
    /// by this process are pointed there).
    #[serde(default)]
    pub advertise_url: Option<String>,
    /// The most machines this process runs at once (absent: as many as are free).
    #[serde(default)]
    pub max_machines: Option<usize>,
}

fn default_lease_s() -> f64 {
    15.0
}

impl FleetConfig {
    /// The process name in the leases.
    pub fn process_name(&self) -> String {
        self.process.clone().unwrap_or_else(|| {
            let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
                .map(|h| h.trim().to_string())
                .unwrap_or_else(|_| "host".to_string());
            format!("{host}-{}", std::process::id())
        })
    }

    /// What a fleet process needs of the rest of the configuration.
    fn check(&self, cfg: &ServiceConfig) -> Result<(), String> {
        if !(1.0..=3600.0).contains(&self.lease_s) {
            return Err(format!(
                "fleet.lease_s must be from 1 to 3600 s, not {}",
                self.lease_s
            ));
        }
        if cfg.database_url.is_none() {
            return Err(
                "[fleet] needs database_url: the processes of a fleet share one \
                        PostgreSQL database"
                    .into(),
            );
        }
        if self.max_machines == Some(0) {
            return Err("fleet.max_machines must be at least 1".into());
        }
        // Their links connect at start in every process: only the lease holder may talk to
        // the NC.
        if let Some(m) = cfg
            .machines
            .iter()
            .find(|m| matches!(m.link, LinkConfig::Mtconnect { .. } | LinkConfig::Opcua(_)))
        {
            return Err(format!(
                "machine '{}': a fleet runs simulated and nc_push machines; an {} link is not \
                 shared between processes yet (run it in a process without [fleet])",
                m.id,
                m.link.kind()
            ));
        }
        Ok(())
    }
}

impl ServiceConfig {
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, ConfigError> {
        let cfg: ServiceConfig = toml::from_str(text).map_err(|e| ConfigError::Parse {
            origin: origin.to_string(),
            message: e.to_string(),
        })?;
        cfg.validate(origin)?;
        Ok(cfg)
    }

    /// The shipped default, or a file.
    pub fn load(path: Option<&std::path::Path>) -> Result<Self, ConfigError> {
        match path {
            None => Self::from_toml(DEFAULT_CONFIG, "config/default.toml (built in)"),
            Some(p) => {
                let text = std::fs::read_to_string(p).map_err(|source| ConfigError::Read {
                    path: p.display().to_string(),
                    source,
                })?;
                Self::from_toml(&text, &p.display().to_string())
            }
        }
    }

    /// Every check of a loaded configuration; run again after command-line overrides, so that
    /// no option bypasses one.
    pub fn validate(&self, origin: &str) -> Result<(), ConfigError> {
        let bad = |m: String| {
            Err(ConfigError::Invalid {
                origin: origin.to_string(),
                message: m,
            })
        };
        if !driftwatch_core::units::positive(self.time_scale) {
            return bad(format!("time_scale must be > 0, not {}", self.time_scale));
        }
        if self.machines.is_empty() {
            return bad("no machines configured".into());
        }
        if !(1..=1 << 20).contains(&self.max_file_mib) {
            return bad(format!(
                "max_file_mib must be from 1 to 1048576 (a recording file's size before it \
                 rotates, MiB), not {}",
                self.max_file_mib
            ));
        }
        if let Err(e) = self.validation.check() {
            return bad(e);
        }

        if let Some(url) = &self.database_url
            && crate::store::Backend::of_url(url).is_none()
        {
            return bad(
                "database_url must be a postgres:// (or sqlite://) URL; leave it out for the \
                 SQLite file in data_dir"
                    .into(),
            );
        }
        if let Err(e) = self.http.check() {
            return bad(e);
        }
        let mut ids: Vec<&str> = self.machines.iter().map(|m| m.id.as_str()).collect();
        ids.sort_unstable();
        if ids.windows(2).any(|w| w[0] == w[1]) {
            return bad("machine ids must be unique".into());
        }
        if let Some(m) = self.machines.iter().find(|m| {
            m.id.is_empty()
                || !m
                    .id
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
        }) {
            return bad(format!(
                "machine id '{}' may hold only letters, digits, '-' and '_'",
                m.id
            ));
        }
        for m in &self.machines {
            if let LinkConfig::Opcua(c) = &m.link
                && let Err(e) = c.check()
            {
                return bad(format!("machine '{}': {e}", m.id));
            }
            if let LinkConfig::NcPush {
                max_ahead_s,
                max_behind_s,
            }
            | LinkConfig::Mtconnect {
                max_ahead_s,
                max_behind_s,
                ..
            } = m.link
                && !(driftwatch_core::units::positive(max_ahead_s)
                    && driftwatch_core::units::positive(max_behind_s)
                    && max_ahead_s <= 86_400.0
                    && max_behind_s <= 30.0 * 86_400.0)
            {
                return bad(format!(
                    "machine '{}': max_ahead_s ({max_ahead_s}) must be in (0, 86400] and max_behind_s ({max_behind_s}) in (0, 2592000]",
                    m.id
                ));
            }
        }
        for m in &self.machines {
            if let Err(e) = validate_mtconnect(&m.link) {
                return bad(format!("machine '{}': {e}", m.id));
            }
        }
        if let Some(f) = &self.fleet
            && let Err(e) = f.check(self)
        {
            return bad(e);
        }
        if let Some(m) = self.machines.iter().find(|m| m.link.is_real())
            && self.time_scale != 1.0
        {
            return bad(format!(
                "time_scale is {}: a real NC ({}) runs on the wall clock, time_scale = 1.0 (machine '{}')",
                self.time_scale,
                m.link.kind(),
                m.id
            ));
        }
        if let Err(e) = self.phase.validate() {
            return bad(e.to_string());
        }
        if let Err(e) = self.schedule.validate() {
            return bad(e.to_string());
        }
        if let Err(e) = driftwatch_machine::alerts::validate_rules(&self.alerts) {
            return bad(e.to_string());
        }
        if let Err(e) = self.thermal.validate() {
            return bad(e);
        }
        if let Err(e) = self.verification.validate() {
            return bad(e);
        }
        for w in &self.webhooks {
            if let Err(e) = w.validate() {
                return bad(e);
            }
        }
        for t in &self.http.tokens {
            if t.token.trim().is_empty() {
                return bad(format!("token of '{}' is empty", t.name));
            }
        }
        Ok(())
    }

    /// What the configuration takes from the environment, checked when a service starts (a
    /// file is checked without it): with `anonymous_read = false`, at least one token usable.
    pub fn check_environment(&self, origin: &str) -> Result<(), ConfigError> {
        if !self.http.anonymous_read && self.resolved_tokens().0.is_empty() {
            return Err(ConfigError::Invalid {
                origin: origin.to_string(),
                message: "http.anonymous_read = false but no token is usable (every tokens \
                          entry is missing or names an environment variable that is not set): \
                          nobody could read the API, the NC included. Set a token or allow \
                          anonymous reads"
                    .into(),
            });
        }
        Ok(())
    }

    /// The webhooks with their `env:` tokens resolved; a webhook whose variable is not set
    /// is sent without a token and named in the second list.
    pub fn resolved_webhooks(
        &self,
    ) -> (
        Vec<(crate::webhook::WebhookConfig, Option<String>)>,
        Vec<String>,
    ) {
        let mut out = Vec::new();
        let mut missing = Vec::new();
        for w in &self.webhooks {
            let token = match w.token.as_deref().map(|t| (t, t.strip_prefix("env:"))) {
                None => None,
                Some((_, Some(var))) => match std::env::var(var) {
                    Ok(v) if !v.trim().is_empty() => Some(v),
                    _ => {
                        missing.push(format!(
                            "webhook {} goes without a token: {var} is not set",
                            w.url
                        ));
                        None
                    }
                },
                Some((t, None)) => Some(t.to_string()),
            };
            out.push((w.clone(), token));
        }
        (out, missing)
    }

    /// The tokens with `env:` references resolved; a token whose variable is not set is
    /// left out (that holder cannot write) and named in the second list.
    pub fn resolved_tokens(&self) -> (Vec<(String, String, Role)>, Vec<String>) {
        let mut ok = Vec::new();
        let mut disabled = Vec::new();
        for t in &self.http.tokens {
            match t.token.strip_prefix("env:") {
                Some(var) => match std::env::var(var) {
                    Ok(v) if !v.trim().is_empty() => ok.push((t.name.clone(), v, t.role)),
                    _ => disabled.push(format!("token of '{}' is off: {var} is not set", t.name)),
                },
                None => ok.push((t.name.clone(), t.token.clone(), t.role)),
            }
        }
        (ok, disabled)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_default_parses_and_runs_one_simulated_machine() {
        let c = ServiceConfig::load(None).unwrap();
        assert_eq!(c.machines.len(), 1);
        assert_eq!(c.http.listen.to_string(), "127.0.0.1:8080");
        assert_eq!(c.time_scale, 60.0);
        assert!(
            matches!(&c.machines[0].link, LinkConfig::Simulated { scenario, .. } if scenario == "two_shift")
        );
        // Every rule kind and setting is in the file, with its default.
        assert_eq!(c.alerts, default_rules());
        assert_eq!(c.verification, Default::default());
        assert_eq!(c.schedule, SchedulePolicy::default());
    }

    #[test]
    fn bad_configurations_are_named() {
        let text = DEFAULT_CONFIG.replace("time_scale = 60.0", "time_scale = 0.0");
        let e = ServiceConfig::from_toml(&text, "t")
            .unwrap_err()
            .to_string();
        assert!(e.contains("time_scale"), "{e}");
        let text = DEFAULT_CONFIG.replace("data_dir", "data_folder");
        assert!(ServiceConfig::from_toml(&text, "t").is_err());
        // The database: the SQLite file unless a PostgreSQL URL is given.
        assert_eq!(
            ServiceConfig::from_toml(DEFAULT_CONFIG, "t")
                .unwrap()
                .database_url,
            None
        );
        let text = DEFAULT_CONFIG.replace("# database_url = ", "database_url = ");
        assert_ne!(text, DEFAULT_CONFIG, "the default documents database_url");
        let c = ServiceConfig::from_toml(&text, "t").unwrap();
        assert!(c.database_url.unwrap().starts_with("postgres://"));
        let text = DEFAULT_CONFIG.replace(
            "data_dir = \"./data\"",
            "data_dir = \"./data\"\ndatabase_url = \"mysql://db/x\"",
        );
        let e = ServiceConfig::from_toml(&text, "t")
            .unwrap_err()
            .to_string();
        assert!(e.contains("database_url"), "{e}");
        let text = DEFAULT_CONFIG.replace("max_gap_min = 60.0", "max_gap_min = 0.0");
        assert_ne!(
            text, DEFAULT_CONFIG,
            "the default documents verification.max_gap_min"
        );
        let e = ServiceConfig::from_toml(&text, "t")
            .unwrap_err()
            .to_string();
        assert!(e.contains("verification.max_gap_min"), "{e}");
    }

    #[test]
    fn the_deployment_example_parses() {
        let text = include_str!("../../../deploy/nc_push.example.toml");
        let c = ServiceConfig::from_toml(text, "deploy/nc_push.example.toml").unwrap();
        assert!(matches!(c.machines[0].link, LinkConfig::NcPush { .. }));
        assert!(!c.http.anonymous_read);
        assert_eq!(c.webhooks.len(), 1);
        // A real NC with a sped-up clock is refused.
        let fast = text.replace("time_scale = 1.0", "time_scale = 60.0");
        let e = ServiceConfig::from_toml(&fast, "t")
            .unwrap_err()
            .to_string();
        assert!(e.contains("nc_push"), "{e}");
    }

    /// The shipped default's commented MTConnect example, in place of the simulated link.
    fn mtconnect_example() -> String {
        // The MTConnect block: from the `[machines.link]` line before its `kind` (the file
        // documents other links' blocks too).
        let lines: Vec<&str> = DEFAULT_CONFIG.lines().collect();
        let kind = lines
            .iter()
            .position(|l| l.starts_with("# kind = \"mtconnect\""))
            .expect("the mtconnect example");
        let block: Vec<&str> = lines[kind - 1..]
            .iter()
            .map_while(|l| l.strip_prefix("# "))
            .collect();
        assert!(block.len() > 5, "{block:?}");
        DEFAULT_CONFIG
            .replace("time_scale = 60.0", "time_scale = 1.0")
            .replace(
                r#"link = { kind = "simulated", scenario = "two_shift" }"#,
                "",
            )
            .replace("\n[phase]", &format!("\n{}\n\n[phase]", block.join("\n")))
    }

    #[test]
    fn the_documented_mtconnect_link_parses_and_is_checked() {
        let text = mtconnect_example();
        let c = ServiceConfig::from_toml(&text, "t").unwrap();
        let LinkConfig::Mtconnect {
            agent,
            device,
            items,
            poll_ms,
            count,
            ..
        } = &c.machines[0].link
        else {
            panic!("{:?}", c.machines[0].link)
        };
        assert_eq!(agent, "http://mtc-agent:5000");
        assert_eq!(device.as_deref(), Some("VMC-1"));
        assert_eq!((*poll_ms, *count), (1000, 1000));
        assert_eq!(items.temperatures["ambient"], "Tamb");
        assert_eq!(items.controller_mode.as_deref(), Some("mode"));
        assert!(c.machines[0].link.is_real());
        for (from, to, says) in [
            (
                "time_scale = 1.0",
                "time_scale = 60.0",
                "a real NC (mtconnect) runs on the wall clock",
            ),
            ("poll_ms = 1000", "poll_ms = 0", "poll_ms"),
            ("count = 1000", "count = 0", "count"),
            ("http://mtc-agent:5000", "mtc-agent:5000", "agent url"),
            (
                r#"controller_mode = "mode""#,
                r#"controller_mode = "exec""#,
                "mapped twice",
            ),
        ] {
            let e = ServiceConfig::from_toml(&text.replace(from, to), "t")
                .unwrap_err()
                .to_string();
            assert!(e.contains(says), "{from} -> {to}: {e}");
        }
        let unknown = text.replace("count = 1000", "count = 1000\nfrom = 5");
        assert!(ServiceConfig::from_toml(&unknown, "t").is_err());
    }

    #[test]
    fn roles_nest() {
        assert!(Role::Admin.allows(Role::Write));
        assert!(Role::Write.allows(Role::Read));
        assert!(!Role::Read.allows(Role::Write));
        assert!(!Role::Write.allows(Role::Admin));
    }
}
