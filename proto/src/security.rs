//! Authentication and access control of distributed runs (DESIGN.md §7).
//!
//! Zenoh authenticates every link with a user name and password (`transport.auth.usrpwd`)
//! and enforces an access-control list (`access_control`) at the router each process
//! connects to. Zenoh 1.10 has no per-user key templates, so the list is generated here
//! from the run's layout — one user, one rule, one subject and one policy per agent
//! process — from the key functions of [`crate::keys`]: what a process may publish is
//! written once, next to the keys themselves.
//!
//! Who may do what (everything under `geese/<run>/`):
//! - everyone (authenticated): subscribe, query, and receive whatever is routed to it;
//! - the world: anything;
//! - the operator (the orchestrator, `geese control`, a controlling viewer): publish on
//!   the control plane, declare the orchestrator's and viewers' presence;
//! - a viewer: declare a viewer's presence;
//! - the agent process speaking for range R: publish its intents and gene batches (R in
//!   the key), declare its own presence tokens, answer detail queries about R;
//! - a router of the mesh, known by its TLS certificate's common name: anything (each
//!   router enforces the list for the processes connected to it; SECURITY.md).
//!
//! A run's [`Secrets`] are a directory of files: `users.txt` (the routers' password
//! dictionary), `acl.json5` (the `access_control` section) and one `<user>.cred` per
//! credential (`user:password`). Passwords come from the operating system's random
//! source (never from the run seed, which is public in the manifest); files are written
//! readable by their owner only, and no password is ever logged or written to a
//! manifest ([`Credential`]'s `Debug` hides it).
use crate::keys::{self, AgentRange};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The world server's user.
pub const WORLD: &str = "world";
/// The operator's user: the orchestrator, `geese control`, a viewer that may control.
pub const OPERATOR: &str = "operator";
/// A read-only viewer's user.
pub const VIEWER: &str = "viewer";
/// Dictionary file name inside a secrets directory.
pub const USERS_FILE: &str = "users.txt";
/// ACL file name inside a secrets directory.
pub const ACL_FILE: &str = "acl.json5";
/// The layout the secrets were made for (no secret in it).
pub const LAYOUT_FILE: &str = "layout.json";

/// The user of the agent process speaking for `r`.
pub fn agents_user(r: AgentRange) -> String {
    format!("agents-{r}")
}

/// The user of router `name` (its links to other routers).
pub fn router_user(name: &str) -> String {
    format!("router-{name}")
}

/// Why secrets could not be made, read or used.
#[derive(Debug, thiserror::Error)]
pub enum SecurityError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: expected one line `user:password` (user of letters, digits, `-`, `_`, `.`), found {found}")]
    BadCredential { path: PathBuf, found: String },
    #[error("{path}, line {line}: expected `user:password`")]
    BadDictionary { path: PathBuf, line: usize },
    #[error("{path}: not a valid access-control section: {reason}")]
    BadAcl { path: PathBuf, reason: String },
    #[error("{path}: not a layout written by `geese secure init`: {reason}")]
    BadLayout { path: PathBuf, reason: String },
    #[error("router name {0:?}: use letters, digits, `-`, `_` and `.`")]
    BadRouterName(String),
    #[error("run name {0:?}: use letters, digits, `-`, `_` and `.`")]
    BadRun(String),
    #[error("agent ranges overlap or leave the run: {0}")]
    BadRanges(String),
    #[error("the operating system's random source failed: {0}")]
    Random(String),
    #[error("{0}")]
    Json(String),
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> SecurityError + '_ {
    move |source| SecurityError::Io { path: path.to_path_buf(), source }
}

fn valid_name(s: &str) -> bool {
    !s.is_empty() && s.len() <= 64 && s.bytes().all(|b| b.is_ascii_alphanumeric() || b"-_.".contains(&b))
}

/// One login: a user name and its password. `Debug` shows the user only.
#[derive(Clone, PartialEq, Eq)]
pub struct Credential {
    pub user: String,
    password: String,
}

impl std::fmt::Debug for Credential {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Credential").field("user", &self.user).field("password", &"<hidden>").finish()
    }
}

impl Credential {
    /// A fresh credential for `user`: 128 random bits from the operating system.
    pub fn generate(user: &str) -> Result<Self, SecurityError> {
        let mut bytes = [0u8; 16];
        getrandom::fill(&mut bytes).map_err(|e| SecurityError::Random(e.to_string()))?;
        let password = bytes.iter().map(|b| format!("{b:02x}")).collect();
        Ok(Credential { user: user.to_string(), password })
    }

    /// A credential with a chosen password (tests: a wrong password).
    pub fn with_password(user: &str, password: &str) -> Self {
        Credential { user: user.into(), password: password.into() }
    }

    /// Read a `<user>.cred` file (`user:password`, one line).
    pub fn read(path: &Path) -> Result<Self, SecurityError> {
        let text = std::fs::read_to_string(path).map_err(io_err(path))?;
        let bad = |found: &str| SecurityError::BadCredential { path: path.to_path_buf(), found: found.into() };
        let mut lines = text.lines().filter(|l| !l.trim().is_empty());
        let (Some(line), None) = (lines.next(), lines.next()) else {
            return Err(bad("no line or several lines"));
        };
        let Some((user, password)) = line.trim().split_once(':') else { return Err(bad("no `:`")) };
        if !valid_name(user) {
            return Err(bad("an invalid user name"));
        }
        if password.is_empty() {
            return Err(bad("an empty password"));
        }
        Ok(Credential { user: user.into(), password: password.into() })
    }

    /// Write it to `path`, readable by its owner only.
    pub fn write(&self, path: &Path) -> Result<(), SecurityError> {
        write_private(path, format!("{}:{}\n", self.user, self.password).as_bytes())
    }

    /// Log in with it: the session's `transport.auth.usrpwd` user and password.
    pub fn apply(&self, c: &mut zenoh::Config) -> Result<(), SecurityError> {
        let quote = |s: &str| serde_json::to_string(s).map_err(|e| SecurityError::Json(e.to_string()));
        c.insert_json5("transport/auth/usrpwd/user", &quote(&self.user)?)
            .and_then(|_| c.insert_json5("transport/auth/usrpwd/password", &quote(&self.password)?))
            .map_err(|e| SecurityError::Json(format!("credential of {}: {e}", self.user)))
    }
}

/// Write `bytes` to a new file (replacing any) with mode 0600.
fn write_private(path: &Path, bytes: &[u8]) -> Result<(), SecurityError> {
    use std::io::Write;
    let mut o = std::fs::OpenOptions::new();
    o.write(true).create(true).truncate(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        o.mode(0o600);
    }
    let mut f = o.open(path).map_err(io_err(path))?;
    f.write_all(bytes).map_err(io_err(path))
}

/// Check a password dictionary (`user:password` per line) and give its path to a
/// listening session (`transport.auth.usrpwd.dictionary_file`).
pub fn apply_dictionary(c: &mut zenoh::Config, path: &Path) -> Result<(), SecurityError> {
    let text = std::fs::read_to_string(path).map_err(io_err(path))?;
    for (i, line) in text.lines().enumerate() {
        let ok = line.trim().is_empty() || line.split_once(':').is_some_and(|(u, p)| valid_name(u) && !p.is_empty());
        if !ok {
            return Err(SecurityError::BadDictionary { path: path.to_path_buf(), line: i + 1 });
        }
    }
    let p = serde_json::to_string(&path.display().to_string()).map_err(|e| SecurityError::Json(e.to_string()))?;
    c.insert_json5("transport/auth/usrpwd/dictionary_file", &p)
        .map_err(|e| SecurityError::Json(format!("{}: {e}", path.display())))
}

/// Read an ACL file (the JSON5 object of Zenoh's `access_control` section) into `c`.
pub fn apply_acl(c: &mut zenoh::Config, path: &Path) -> Result<(), SecurityError> {
    let text = std::fs::read_to_string(path).map_err(io_err(path))?;
    c.insert_json5("access_control", &text)
        .map_err(|e| SecurityError::BadAcl { path: path.to_path_buf(), reason: e.to_string() })
}

/// Who takes part in a run, as the access-control list needs it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Layout {
    pub run: String,
    /// The id range of every agent process (disjoint).
    pub agents: Vec<AgentRange>,
    /// Names of the routers of a mesh; empty on one host. Router links use mutual TLS
    /// (over QUIC):
    /// a router logs in as `router-<name>` and is known by its certificate's common
    /// name, `router-<name>` (the password login is one-way — only the router that
    /// opens a link presents one — while both ends of a TLS link see the other's
    /// certificate).
    pub routers: Vec<String>,
}

impl Layout {
    /// `agents` agents in processes of `per_process` (the last may hold fewer).
    pub fn even(run: &str, agents: u32, per_process: u32) -> Layout {
        let per = per_process.max(1);
        let ranges = (0..agents)
            .step_by(per as usize)
            .filter_map(|first| AgentRange::new(first, per.min(agents - first)))
            .collect();
        Layout { run: run.into(), agents: ranges, routers: Vec::new() }
    }

    fn check(&self) -> Result<(), SecurityError> {
        if !keys::valid_run_name(&self.run) {
            return Err(SecurityError::BadRun(self.run.clone()));
        }
        if let Some(r) = self.routers.iter().find(|r| !valid_name(r)) {
            return Err(SecurityError::BadRouterName(r.clone()));
        }
        let mut sorted = self.agents.clone();
        sorted.sort();
        if let Some(w) = sorted.windows(2).find(|w| w[0].last >= w[1].first) {
            return Err(SecurityError::BadRanges(format!("{} and {}", w[0], w[1])));
        }
        Ok(())
    }

    /// Every user of the run.
    pub fn users(&self) -> Vec<String> {
        let mut u: Vec<String> = [WORLD, OPERATOR, VIEWER].iter().map(|s| s.to_string()).collect();
        u.extend(self.agents.iter().map(|r| agents_user(*r)));
        u.extend(self.routers.iter().map(|r| router_user(r)));
        u
    }

    /// The `access_control` section enforcing DESIGN.md §7 for this layout.
    pub fn acl(&self) -> Acl {
        let run = &self.run;
        let all = format!("{}/**", keys::run_prefix(run));
        let mut acl = Acl::default();
        // Everyone reads: subscribes and queries (ingress), and gets what is routed to
        // it (egress). Reading never needs `put` ingress: that would let it forge.
        acl.rule(
            "read-in",
            &[&all],
            &["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query", "query"],
            Some("ingress"),
        );
        acl.rule("read-out", &[&all], ALL_MESSAGES, Some("egress"));
        acl.subject("everyone", None);
        acl.policy(&["read-in", "read-out"], &["everyone"]);

        acl.rule("world", &[&all], ALL_MESSAGES, Some("ingress"));
        acl.subject("world", Some(WORLD));
        acl.policy(&["world"], &["world"]);

        let ctl = format!("{}/ctl/**", keys::run_prefix(run));
        let viewers = keys::viewer_presence(run, "*");
        acl.rule("operator-put", &[&ctl], &["put"], Some("ingress"));
        acl.rule(
            "operator-tokens",
            &[&keys::orchestrator_presence(run), &viewers],
            &["liveliness_token"],
            Some("ingress"),
        );
        acl.subject("operator", Some(OPERATOR));
        acl.policy(&["operator-put", "operator-tokens"], &["operator"]);

        acl.rule("viewer-tokens", &[&viewers], &["liveliness_token"], Some("ingress"));
        acl.subject("viewer", Some(VIEWER));
        acl.policy(&["viewer-tokens"], &["viewer"]);

        for r in &self.agents {
            let user = agents_user(*r);
            let put_id = format!("{user}-put");
            let tok_id = format!("{user}-tokens");
            let det_id = format!("{user}-detail");
            let gene_cells = format!("{}/cell/*/*/genes/{r}", keys::run_prefix(run));
            acl.rule(
                &put_id,
                &[&keys::agents_action(run, *r), &keys::agents_genes(run, *r), &gene_cells],
                &["put"],
                Some("ingress"),
            );
            acl.rule(
                &tok_id,
                &[&keys::agents_presence(run, *r), &keys::cells_presence(run, *r)],
                &["liveliness_token"],
                Some("ingress"),
            );
            acl.rule(&det_id, &[&keys::agents_detail(run, *r)], &["declare_queryable", "reply"], Some("ingress"));
            acl.subject(&user, Some(&user));
            acl.policy(&[&put_id, &tok_id, &det_id], &[&user]);
        }
        for name in &self.routers {
            let user = router_user(name);
            acl.rule(&user, &["**"], ALL_MESSAGES, None);
            acl.subjects.push(AclSubject {
                id: user.clone(),
                usernames: None,
                cert_common_names: Some(vec![user.clone()]),
            });
            acl.policy(&[&user], &[&user]);
        }
        acl
    }
}

/// Every message kind of Zenoh's access control.
const ALL_MESSAGES: &[&str] = &[
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
];

/// Zenoh's `access_control` section, as written into `acl.json5`.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Acl {
    pub enabled: bool,
    pub default_permission: &'static str,
    pub rules: Vec<AclRule>,
    pub subjects: Vec<AclSubject>,
    pub policies: Vec<AclPolicy>,
}

impl Default for Acl {
    fn default() -> Self {
        Acl { enabled: true, default_permission: "deny", rules: Vec::new(), subjects: Vec::new(), policies: Vec::new() }
    }
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct AclRule {
    pub id: String,
    pub messages: Vec<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub flows: Option<Vec<String>>,
    pub key_exprs: Vec<String>,
    pub permission: &'static str,
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct AclSubject {
    pub id: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub usernames: Option<Vec<String>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cert_common_names: Option<Vec<String>>,
}

#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct AclPolicy {
    pub rules: Vec<String>,
    pub subjects: Vec<String>,
}

impl Acl {
    fn rule(&mut self, id: &str, keys: &[&str], messages: &[&str], flow: Option<&str>) {
        self.rules.push(AclRule {
            id: id.into(),
            messages: messages.iter().map(|s| s.to_string()).collect(),
            flows: flow.map(|f| vec![f.to_string()]),
            key_exprs: keys.iter().map(|s| s.to_string()).collect(),
            permission: "allow",
        });
    }
    fn subject(&mut self, id: &str, user: Option<&str>) {
        self.subjects.push(AclSubject {
            id: id.into(),
            usernames: user.map(|u| vec![u.to_string()]),
            cert_common_names: None,
        });
    }
    fn policy(&mut self, rules: &[&str], subjects: &[&str]) {
        self.policies.push(AclPolicy {
            rules: rules.iter().map(|s| s.to_string()).collect(),
            subjects: subjects.iter().map(|s| s.to_string()).collect(),
        });
    }

    /// As JSON (valid JSON5), one rule per line.
    pub fn to_json(&self) -> Result<String, SecurityError> {
        serde_json::to_string_pretty(self).map_err(|e| SecurityError::Json(e.to_string()))
    }
}

/// [`Layout`] as `layout.json` holds it.
#[derive(Serialize, Deserialize)]
struct LayoutFile {
    run: String,
    agents: Vec<String>,
    routers: Vec<String>,
}

/// A run's secrets directory: the routers' dictionary and ACL and one credential file
/// per user. A temporary one ([`Secrets::temporary`]) is removed when dropped.
#[derive(Debug)]
pub struct Secrets {
    dir: PathBuf,
    remove_on_drop: bool,
    layout: Layout,
}

impl Secrets {
    /// Make the secrets of `layout` in `dir` (created, mode 0700): fresh passwords for
    /// every user, the dictionary and the ACL.
    pub fn generate(layout: &Layout, dir: &Path) -> Result<Secrets, SecurityError> {
        layout.check()?;
        std::fs::create_dir_all(dir).map_err(io_err(dir))?;
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(dir, std::fs::Permissions::from_mode(0o700)).map_err(io_err(dir))?;
        }
        let secrets = Secrets { dir: dir.to_path_buf(), remove_on_drop: false, layout: layout.clone() };
        let mut dictionary = String::new();
        for user in layout.users() {
            let c = Credential::generate(&user)?;
            c.write(&secrets.credential(&user))?;
            dictionary.push_str(&format!("{}:{}\n", c.user, c.password));
        }
        write_private(&secrets.users(), dictionary.as_bytes())?;
        write_private(&secrets.acl(), layout.acl().to_json()?.as_bytes())?;
        let file = LayoutFile {
            run: layout.run.clone(),
            agents: layout.agents.iter().map(|r| r.to_string()).collect(),
            routers: layout.routers.clone(),
        };
        let json = serde_json::to_string_pretty(&file).map_err(|e| SecurityError::Json(e.to_string()))?;
        let p = dir.join(LAYOUT_FILE);
        std::fs::write(&p, json).map_err(io_err(&p))?;
        Ok(secrets)
    }

    /// The secrets of `layout` in a new private directory under the system's temporary
    /// directory, removed when the returned value is dropped.
    pub fn temporary(layout: &Layout) -> Result<Secrets, SecurityError> {
        let mut tag = [0u8; 8];
        getrandom::fill(&mut tag).map_err(|e| SecurityError::Random(e.to_string()))?;
        let tag: String = tag.iter().map(|b| format!("{b:02x}")).collect();
        let dir = std::env::temp_dir().join(format!("geese-secrets-{}-{tag}", layout.run));
        let mut s = Secrets::generate(layout, &dir)?;
        s.remove_on_drop = true;
        Ok(s)
    }

    /// Secrets made earlier (`geese secure init`).
    pub fn open(dir: &Path) -> Result<Secrets, SecurityError> {
        for f in [USERS_FILE, ACL_FILE] {
            let p = dir.join(f);
            std::fs::metadata(&p).map_err(io_err(&p))?;
        }
        let p = dir.join(LAYOUT_FILE);
        let text = std::fs::read_to_string(&p).map_err(io_err(&p))?;
        let bad = |reason: String| SecurityError::BadLayout { path: p.clone(), reason };
        let file: LayoutFile = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
        let agents = file
            .agents
            .iter()
            .map(|r| AgentRange::parse(r).ok_or_else(|| bad(format!("agent range {r:?}"))))
            .collect::<Result<_, _>>()?;
        let layout = Layout { run: file.run, agents, routers: file.routers };
        layout.check()?;
        Ok(Secrets { dir: dir.to_path_buf(), remove_on_drop: false, layout })
    }

    /// Who the secrets were made for.
    pub fn layout(&self) -> &Layout {
        &self.layout
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }
    /// The credential file of `user`.
    pub fn credential(&self, user: &str) -> PathBuf {
        self.dir.join(format!("{user}.cred"))
    }
    pub fn users(&self) -> PathBuf {
        self.dir.join(USERS_FILE)
    }
    pub fn acl(&self) -> PathBuf {
        self.dir.join(ACL_FILE)
    }
}

impl Drop for Secrets {
    fn drop(&mut self) {
        if self.remove_on_drop {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn credentials_round_trip_and_hide_their_password() {
        let dir = std::env::temp_dir().join(format!("geese-sec-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let c = Credential::generate("agents-0-9").unwrap();
        let p = dir.join("a.cred");
        c.write(&p).unwrap();
        assert_eq!(Credential::read(&p).unwrap(), c);
        assert!(!format!("{c:?}").contains(&c.password));
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            assert_eq!(std::fs::metadata(&p).unwrap().permissions().mode() & 0o777, 0o600);
        }
        for bad in ["", "nopassword", "us er:pw", "u:", "a:b\nc:d"] {
            std::fs::write(&p, bad).unwrap();
            let e = Credential::read(&p).unwrap_err().to_string();
            assert!(e.contains("a.cred"), "{bad:?}: {e}");
        }
        assert_ne!(Credential::generate("x").unwrap(), Credential::generate("x").unwrap());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_acl_lets_each_agent_process_publish_on_its_own_keys_only() {
        let l = Layout::even("r1", 10, 4);
        assert_eq!(l.agents.iter().map(|r| r.to_string()).collect::<Vec<_>>(), ["0-3", "4-7", "8-9"]);
        let acl = l.acl();
        let rule = |id: &str| acl.rules.iter().find(|r| r.id == id).unwrap();
        assert_eq!(
            rule("agents-4-7-put").key_exprs,
            ["geese/r1/agent/4-7/action", "geese/r1/agent/4-7/genes", "geese/r1/cell/*/*/genes/4-7"]
        );
        assert_eq!(rule("agents-4-7-put").flows.as_deref(), Some(&["ingress".to_string()][..]));
        // Nobody but the operator and the world may put on the control plane.
        let ctl_puts: Vec<&str> = acl
            .rules
            .iter()
            .filter(|r| r.messages.iter().any(|m| m == "put") && r.flows.as_deref() != Some(&["egress".into()]))
            .filter(|r| r.key_exprs.iter().any(|k| k.contains("/ctl/") || k.ends_with("/**")))
            .map(|r| r.id.as_str())
            .collect();
        assert_eq!(ctl_puts, ["world", "operator-put"]);
        // Zenoh accepts the section as it is written.
        let mut c = zenoh::Config::default();
        c.insert_json5("access_control", &acl.to_json().unwrap()).unwrap();
        let overlapping =
            Layout { agents: vec![AgentRange::new(0, 5).unwrap(), AgentRange::new(4, 2).unwrap()], ..l.clone() };
        assert!(matches!(Secrets::temporary(&overlapping), Err(SecurityError::BadRanges(_))));
    }

    #[test]
    fn temporary_secrets_hold_every_user_and_go_away() {
        let l = Layout { routers: vec!["h1".into()], ..Layout::even("r2", 4, 2) };
        let dir;
        {
            let s = Secrets::temporary(&l).unwrap();
            dir = s.dir().to_path_buf();
            let dict = std::fs::read_to_string(s.users()).unwrap();
            for u in ["world", "operator", "viewer", "agents-0-1", "agents-2-3", "router-h1"] {
                assert!(dict.lines().any(|line| line.starts_with(&format!("{u}:"))), "{u}");
                assert_eq!(Credential::read(&s.credential(u)).unwrap().user, u);
            }
            let mut c = zenoh::Config::default();
            apply_dictionary(&mut c, &s.users()).unwrap();
            apply_acl(&mut c, &s.acl()).unwrap();
            std::fs::write(s.acl(), "{ enabled: true, rules: [ { id: 1 } ] }").unwrap();
            let e = apply_acl(&mut c, &s.acl()).unwrap_err().to_string();
            assert!(e.contains("acl.json5") && e.contains("not a valid access-control section"), "{e}");
        }
        assert!(!dir.exists());
    }
}
