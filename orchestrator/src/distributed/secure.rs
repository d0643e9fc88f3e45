//! `geese secure init`: the credentials and access-control list of a run whose processes
//! are started by hand or on several hosts (DESIGN.md §7, §9).
//!
//! `geese run --processes N` makes its own per-run secrets and needs none of this; a
//! multi-host run, or one through an external router, has its routers check logins
//! against one dictionary and enforce one list, both written here, and every process
//! given its own credential file (`--credentials FILE`).
use anyhow::{bail, Context, Result};
use geese_proto::keys::AgentRange;
use geese_proto::security::{self, Layout, Secrets};
use std::path::PathBuf;

#[derive(clap::Subcommand, Debug)]
pub enum SecureCmd {
    /// Make a run's secrets: one credential per process (world, operator, viewer, each
    /// agent process, each router), the routers' password dictionary and the
    /// access-control list.
    Init(InitArgs),
}

#[derive(clap::Args, Debug)]
pub struct InitArgs {
    /// The run name the list is written for (`geese run --run-name`).
    #[arg(long)]
    pub run: String,
    /// Agents of the run.
    #[arg(long)]
    pub agents: u32,
    /// Agents per agent process (each process gets the ids FIRST..FIRST+K-1, in order)
    /// [default: all in one].
    #[arg(long, value_name = "K")]
    pub per_process: Option<u32>,
    /// Agent processes' id ranges instead, e.g. `0-49,50-99,100` (disjoint).
    #[arg(long, value_name = "RANGES", conflicts_with = "per_process")]
    pub ranges: Option<String>,
    /// Names of the routers of a mesh (comma-separated): each gets a `router-NAME` login
    /// for its links to the others.
    /// Their links use mutual TLS over QUIC, and a router is known by its certificate's common
    /// name `router-NAME` (deploy/tls/make-test-ca.sh makes test certificates).
    #[arg(long, value_delimiter = ',')]
    pub routers: Vec<String>,
    /// Directory to write (created, readable by its owner only).
    #[arg(long)]
    pub out: PathBuf,
}

/// Parse `0-49,50-99,100`.
fn parse_ranges(s: &str, agents: u32) -> Result<Vec<AgentRange>> {
    let mut v = Vec::new();
    for chunk in s.split(',').map(str::trim).filter(|c| !c.is_empty()) {
        let r = AgentRange::parse(chunk)
            .with_context(|| format!("--ranges: {chunk:?} is not an id or FIRST-LAST with FIRST < LAST"))?;
        if !r.within(agents) {
            bail!("--ranges: {chunk} lies outside the run's ids 0..{agents}");
        }
        v.push(r);
    }
    Ok(v)
}

pub fn secure_cmd(cmd: SecureCmd) -> Result<()> {
    match cmd {
        SecureCmd::Init(a) => {
            if a.agents == 0 {
                bail!("--agents must be at least 1");
            }
            let mut layout = match (&a.ranges, a.per_process) {
                (Some(r), _) => Layout { run: a.run.clone(), agents: parse_ranges(r, a.agents)?, routers: Vec::new() },
                (None, Some(0)) => bail!("--per-process must be at least 1"),
                (None, per) => Layout::even(&a.run, a.agents, per.unwrap_or(a.agents)),
            };
            layout.routers = a.routers.clone();
            let started = std::time::Instant::now();
            let s = Secrets::generate(&layout, &a.out)?;
            let acl_bytes = std::fs::metadata(s.acl()).map(|m| m.len()).unwrap_or(0);
            let acl = layout.acl();
            println!(
                "{}: {} credentials, {} ({} rules, {} subjects, {} policies, {:.1} kB) in {:.0} ms",
                s.dir().display(),
                layout.users().len(),
                security::ACL_FILE,
                acl.rules.len(),
                acl.subjects.len(),
                acl.policies.len(),
                acl_bytes as f64 / 1000.0,
                started.elapsed().as_secs_f64() * 1000.0
            );
            println!("routers:        --users {} --acl {}", s.users().display(), s.acl().display());
            println!("world:          --credentials {}", s.credential(security::WORLD).display());
            println!(
                "geese run, geese control, a controlling viewer: --credentials {}",
                s.credential(security::OPERATOR).display()
            );
            println!("read-only viewer: --credentials {}", s.credential(security::VIEWER).display());
            for r in &layout.agents {
                println!("agents {r}: --credentials {}", s.credential(&security::agents_user(*r)).display());
            }
            for name in &layout.routers {
                println!("router {name}: --credentials {}", s.credential(&security::router_user(name)).display());
            }
            Ok(())
        }
    }
}
