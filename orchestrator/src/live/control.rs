//! `geese control`: send a control-plane command to a running distributed world.
//!
//! Why this exists: a researcher watching a swarm run over Zenoh wants to perturb it
//! now — add obstacles, change IP, switch lateral transfer, drop genes, kill agents —
//! without having planned it in the configuration. The world already applies a
//! [`Control::Schedule`] received on `geese/<run>/ctl/schedule` between two steps,
//! exactly as a perturbation from the configuration (REFERENCE §8.4); this command asks
//! the world which step it is at and what its arena is, checks the request against them
//! with the rule the world applies ([`Control::validate`]) and publishes it.
use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use geese_proto::zenoh_bus::{self, CommonArgs, Role};
use geese_proto::{encode, keys, Control, Geometry, InvalidCommand, Perturbation};
use std::time::Duration;

#[derive(Args, Debug)]
pub struct ControlArgs {
    /// Name of the run (`geese run --run-name`, or the launcher's generated name).
    #[arg(long)]
    pub run: String,
    /// How long to look for the world, in milliseconds.
    #[arg(long, default_value_t = 5000)]
    pub timeout_ms: u64,
    #[command(flatten)]
    pub zenoh: CommonArgs,
    #[command(subcommand)]
    pub cmd: ControlCmd,
}

#[derive(Subcommand, Debug, Clone, PartialEq)]
pub enum ControlCmd {
    /// Schedule a perturbation, applied right after step `--at` (default: the next step
    /// the world runs, so it is in force from the one after). The world keeps running
    /// while the message travels: if it has passed `--at` when the message arrives, the
    /// change applies at once, between two steps.
    Perturb {
        #[arg(long)]
        at: Option<u64>,
        #[command(flatten)]
        change: ChangeArgs,
    },
    /// Stop the run after the current step (every process exits).
    Stop,
    /// Hold the run between two steps (the live viewer's Pause).
    Pause,
    /// Go on after a pause.
    Resume,
    /// Make at most RATE steps per second (0: no limit).
    StepRate { rate: f64 },
}

/// Exactly one change.
#[derive(Args, Debug, Clone, PartialEq)]
#[group(required = true, multiple = false)]
pub struct ChangeArgs {
    /// Add obstacles: COUNT or COUNT:RADIUS (radius 10 by default); they stay.
    #[arg(long, value_name = "COUNT[:RADIUS]")]
    pub add_obstacles: Option<String>,
    /// Set the interaction probability IP (in [0, 1]).
    #[arg(long)]
    pub ip: Option<f64>,
    /// Switch lateral transfer on or off.
    #[arg(long, value_name = "on|off")]
    pub lateral_transfer: Option<String>,
    /// Set the gene-message loss probability (in [0, 1]).
    #[arg(long)]
    pub gene_loss: Option<f64>,
    /// Kill this fraction (in (0, 1]) of the live agents.
    #[arg(long)]
    pub kill: Option<f64>,
    /// Turn the world to this task (foraging or nest): the old task's items and places
    /// go, the new task's come. The world refuses a switch to the task it is running.
    #[arg(long, value_name = "foraging|nest")]
    pub switch_task: Option<String>,
}

/// The flag of a field [`Control::validate`] refused.
fn flag(e: &InvalidCommand) -> &'static str {
    match e.field.split('.').next() {
        Some("AddObstacles") => "--add-obstacles",
        Some("SetIp") => "--ip",
        Some("SetGeneLoss") => "--gene-loss",
        Some("KillFraction") => "--kill",
        Some("Schedule") => "--at",
        _ => "the command",
    }
}

impl ChangeArgs {
    /// The perturbation asked for, parsed; errors name the flag. Its values are checked
    /// against the world's arena by [`message`] ([`Perturbation::validate`]); here only
    /// what would change nothing (no obstacle, no agent killed) is refused as well.
    pub fn perturbation(&self) -> Result<Perturbation> {
        if let Some(spec) = &self.add_obstacles {
            let (count, radius) = match spec.split_once(':') {
                Some((c, r)) => (c, r),
                None => (spec.as_str(), "10"),
            };
            let count: u32 =
                count.trim().parse().with_context(|| format!("--add-obstacles {spec:?}: COUNT must be an integer"))?;
            let radius: i32 = radius
                .trim()
                .parse()
                .with_context(|| format!("--add-obstacles {spec:?}: RADIUS must be an integer"))?;
            if count == 0 {
                bail!("--add-obstacles {spec:?}: COUNT 0 adds nothing");
            }
            return Ok(Perturbation::AddObstacles { count, radius });
        }
        if let Some(p) = self.ip {
            return Ok(Perturbation::SetIp(p));
        }
        if let Some(v) = &self.lateral_transfer {
            return match v.as_str() {
                "on" | "true" => Ok(Perturbation::SetLateralTransfer(true)),
                "off" | "false" => Ok(Perturbation::SetLateralTransfer(false)),
                _ => bail!("--lateral-transfer {v:?}: expected on or off"),
            };
        }
        if let Some(p) = self.gene_loss {
            return Ok(Perturbation::SetGeneLoss(p));
        }
        if let Some(t) = &self.switch_task {
            let task: geese_proto::Task = t.parse().map_err(|e: String| anyhow::anyhow!("--switch-task: {e}"))?;
            return Ok(Perturbation::SwitchTask(task));
        }
        if let Some(f) = self.kill {
            if f == 0.0 {
                bail!("--kill 0: kills nothing");
            }
            return Ok(Perturbation::KillFraction(f));
        }
        bail!("no change given")
    }
}

/// Build the control message for a world of geometry `geom` that runs `next_step` next,
/// checked as the world checks it ([`Control::validate`]); errors name the flag.
pub fn message(cmd: &ControlCmd, next_step: u64, geom: &Geometry) -> Result<(&'static str, Control)> {
    match cmd {
        ControlCmd::Stop => Ok(("stop", Control::Stop)),
        ControlCmd::Pause => Ok(("view", Control::Pause)),
        ControlCmd::Resume => Ok(("view", Control::Resume)),
        ControlCmd::StepRate { rate } => {
            geese_proto::limits::check_step_rate(*rate).map_err(|e| anyhow::anyhow!("step-rate: {e}"))?;
            Ok(("view", Control::StepRate(*rate)))
        }
        ControlCmd::Perturb { at, change } => {
            let change = change.perturbation()?;
            let at_step = at.unwrap_or(next_step);
            if at_step < next_step {
                bail!("--at {at_step}: the world is already at step {next_step}; choose a step ≥ {next_step}");
            }
            let msg = Control::Schedule { at_step, change };
            msg.validate(geom).map_err(|e| anyhow::anyhow!("{}: {e}", flag(&e)))?;
            Ok(("schedule", msg))
        }
    }
}

pub fn control_cmd(args: ControlArgs) -> Result<()> {
    if let ControlCmd::Perturb { change, .. } = &args.cmd {
        change.perturbation()?;
    }
    // The router drops control messages of anyone else without telling the sender: say
    // so here rather than report a command sent that nobody will receive.
    if let Some(p) = &args.zenoh.credentials {
        let user = geese_proto::security::Credential::read(p)?.user;
        if user != geese_proto::security::OPERATOR {
            bail!(
                "--credentials {}: logs in as {user:?}; only the operator credential may use the control plane",
                p.display()
            );
        }
    }
    let rt = zenoh_bus::runtime(1)?;
    rt.block_on(async move {
        let session = open_or_explain(&args.zenoh).await?;
        let result = async {
            let (info, _) =
                zenoh_bus::fetch_run_info(&session, &args.run, Duration::from_millis(args.timeout_ms)).await?;
            let (what, msg) = message(&args.cmd, info.next_step, &info.geometry)?;
            zenoh_bus::put(&session, &keys::ctl(&args.run, what), encode(&msg)?).await?;
            println!("geese control: sent {msg:?} to run {} (world at step {})", args.run, info.next_step);
            anyhow::Ok(())
        }
        .await;
        // Let the put leave before the session closes.
        tokio::time::sleep(Duration::from_millis(200)).await;
        let _ = session.close().await;
        result
    })
}

/// How long `geese control` waits for its session before saying why it has none: a
/// router refuses a client without a login by closing the link, which Zenoh retries
/// for 15 s and then reports as an unreachable endpoint.
pub const OPEN_WAIT: Duration = Duration::from_secs(3);

/// Open the session, or say within [`OPEN_WAIT`] why not, in the user's terms.
async fn open_or_explain(z: &CommonArgs) -> Result<zenoh::Session> {
    // Zenoh's own connect timeout (its open does not yield to a Tokio timeout), unless
    // the user set one.
    let mut quick = z.clone();
    if !z.cfg.iter().any(|c| c.starts_with("connect/timeout_ms:")) {
        quick.cfg.push(format!("connect/timeout_ms:{}", OPEN_WAIT.as_millis()));
    }
    let cause = match zenoh_bus::open(&quick, Role::Client).await {
        Ok(s) => return Ok(s),
        Err(e) => e.to_string(),
    };
    let endpoints: Vec<&String> = z.router.iter().chain(&z.connect).collect();
    let listening: Vec<&String> = endpoints.iter().copied().filter(|e| tcp_listens(e)).collect();
    Err(match (&z.credentials, listening.first()) {
        (None, Some(e)) => anyhow::anyhow!(
            "the world's router at {e} accepted the connection but refused the session: the run is \
             authenticated (runs started by `geese run --processes N` are, unless --insecure) and this \
             command logged in as nobody. Pass the operator credential: --credentials FILE, the file \
             named on the launcher's line `control: geese control … --credentials FILE` ({cause})"
        ),
        (_, None) if !endpoints.is_empty() => anyhow::anyhow!(
            "nothing accepts connections at {}: is the run still going, and is -e the locator the \
             launcher printed? ({cause})",
            endpoints.iter().map(|e| e.as_str()).collect::<Vec<_>>().join(", ")
        ),
        _ => anyhow::anyhow!("cannot open the zenoh session: {cause}"),
    })
}

/// Whether a TCP listener answers at `tcp/HOST:PORT` within a second (other link kinds
/// are not probed: `false`).
fn tcp_listens(endpoint: &str) -> bool {
    use std::net::ToSocketAddrs;
    let Some(addr) = endpoint.strip_prefix("tcp/") else { return false };
    let addr = addr.split('#').next().unwrap_or(addr);
    let Ok(mut addrs) = addr.to_socket_addrs() else { return false };
    addrs.any(|a| std::net::TcpStream::connect_timeout(&a, Duration::from_secs(1)).is_ok())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn change() -> ChangeArgs {
        ChangeArgs {
            add_obstacles: None,
            ip: None,
            lateral_transfer: None,
            gene_loss: None,
            kill: None,
            switch_task: None,
        }
    }

    fn arena() -> Geometry {
        Geometry::new(100, 100, 10).unwrap()
    }

    /// The error of perturbing with `c` a world at step 1.
    fn refused(c: ChangeArgs) -> String {
        message(&ControlCmd::Perturb { at: None, change: c }, 1, &arena()).unwrap_err().to_string()
    }

    #[test]
    fn changes_are_validated_and_named() {
        let c = ChangeArgs { add_obstacles: Some("3:5".into()), ..change() };
        assert_eq!(c.perturbation().unwrap(), Perturbation::AddObstacles { count: 3, radius: 5 });
        let c = ChangeArgs { add_obstacles: Some("2".into()), ..change() };
        assert_eq!(c.perturbation().unwrap(), Perturbation::AddObstacles { count: 2, radius: 10 });
        for bad in ["x", "2:y", "0", "2:-1", "4294967295:10", "1000000000000", "1:101"] {
            let e = refused(ChangeArgs { add_obstacles: Some(bad.into()), ..change() });
            assert!(e.contains("--add-obstacles"), "{bad}: {e}");
        }
        assert_eq!(
            refused(ChangeArgs { add_obstacles: Some("4294967295:10".into()), ..change() }),
            "--add-obstacles: AddObstacles.count 4294967295 exceeds 1000"
        );
        for bad in [1.5, -0.1, f64::NAN, f64::INFINITY] {
            assert!(refused(ChangeArgs { ip: Some(bad), ..change() }).starts_with("--ip: SetIp"), "{bad}");
            assert!(refused(ChangeArgs { gene_loss: Some(bad), ..change() }).starts_with("--gene-loss: SetGeneLoss"));
            assert!(refused(ChangeArgs { kill: Some(bad), ..change() }).starts_with("--kill: KillFraction"));
        }
        let e = refused(ChangeArgs { ip: Some(f64::NAN), ..change() });
        assert_eq!(e, "--ip: SetIp NaN is not in [0, 1]");
        let e = ChangeArgs { ip: Some(1.5), ..change() };
        let e = message(&ControlCmd::Perturb { at: Some(u64::MAX), change: e }, 1, &arena()).unwrap_err();
        assert!(e.to_string().starts_with("--at: Schedule.at_step 18446744073709551615 exceeds"), "{e}");
        let e = ChangeArgs { lateral_transfer: Some("maybe".into()), ..change() }.perturbation().unwrap_err();
        assert!(e.to_string().contains("--lateral-transfer"), "{e}");
        assert_eq!(
            ChangeArgs { lateral_transfer: Some("off".into()), ..change() }.perturbation().unwrap(),
            Perturbation::SetLateralTransfer(false)
        );
        let e = ChangeArgs { kill: Some(0.0), ..change() }.perturbation().unwrap_err();
        assert!(e.to_string().contains("--kill"), "{e}");
        let ok = ChangeArgs { add_obstacles: Some("1000:100".into()), ..change() };
        assert!(message(&ControlCmd::Perturb { at: None, change: ok }, 1, &arena()).is_ok());
    }

    #[test]
    fn schedule_defaults_to_the_next_step_and_refuses_the_past() {
        let cmd = ControlCmd::Perturb { at: None, change: ChangeArgs { ip: Some(0.5), ..change() } };
        assert_eq!(
            message(&cmd, 42, &arena()).unwrap(),
            ("schedule", Control::Schedule { at_step: 42, change: Perturbation::SetIp(0.5) })
        );
        let past = ControlCmd::Perturb { at: Some(10), change: ChangeArgs { ip: Some(0.5), ..change() } };
        assert!(message(&past, 42, &arena()).unwrap_err().to_string().contains("already at step 42"));
        assert_eq!(message(&ControlCmd::Stop, 7, &arena()).unwrap(), ("stop", Control::Stop));
        assert_eq!(message(&ControlCmd::Pause, 7, &arena()).unwrap(), ("view", Control::Pause));
        let rate = |rate| message(&ControlCmd::StepRate { rate }, 7, &arena());
        assert_eq!(rate(12.5).unwrap(), ("view", Control::StepRate(12.5)));
        assert!(rate(-1.0).unwrap_err().to_string().starts_with("step-rate: StepRate -1"));
        assert!(rate(1e-300).unwrap_err().to_string().contains("is neither 0 nor in [0.01, 10000]"));
    }
}
