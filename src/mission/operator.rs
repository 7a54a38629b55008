//! The operator console over zenoh: `moonhaul mission start | stop | status`.
//!
//! The console holds the team's key file, so it authenticates what it hears and signs what it
//! says. It has no clock of its own in the team's time base (a simulated mission runs on the
//! world's time): it listens to the units first and stamps its commands with the newest unit
//! stamp it accepted plus the time since it heard it. A start names a mission number that must
//! exceed every earlier one; the console uses the Unix time in seconds, so starts from any
//! console increase. A stop is sent several times (it is idempotent, and a stop under a valid
//! key always wins at the units).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use moonhaul_coord::auth::{KeyFile, Sealer};
use moonhaul_coord::message::{
    Body, Envelope, OperatorCommand, Sender, UnitTick, PROTOCOL_VERSION,
};
use moonhaul_coord::Validator;
use moonhaul_core::state::Phase;
use moonhaul_deploy::cli_support::wall_us;
use moonhaul_deploy::network::{self, Access, Keys, NetworkSettings, Role};

#[derive(Debug, clap::Args)]
pub struct ConsoleArgs {
    /// The team's key file (`moonhaul keys generate`).
    #[arg(long, value_name = "FILE")]
    pub keys: PathBuf,
    /// Zenoh endpoint of any team member (repeatable).
    #[arg(long, value_name = "ENDPOINT", default_value = "tcp/127.0.0.1:7447")]
    pub connect: Vec<String>,
    /// How long to listen to the units first, s.
    #[arg(long, default_value_t = 1.0, value_name = "S")]
    pub listen_s: f64,
}

/// What the console knows of a unit.
#[derive(Debug, Clone, Copy)]
pub struct UnitView {
    pub tick: UnitTick,
    pub stamp_us: u64,
    pub heard: Instant,
}

/// An operator session on a team.
pub struct Console {
    session: zenoh::Session,
    publisher: zenoh::pubsub::Publisher<'static>,
    states: zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    validator: Validator,
    sealer: Sealer,
    team: String,
    team_size: usize,
    seq: u64,
    pub units: BTreeMap<usize, UnitView>,
}

impl Console {
    pub async fn open(keys_path: &std::path::Path, connect: &[String]) -> Result<Console> {
        let keys = KeyFile::load(keys_path)?;
        let access = Access::new(&keys, Role::Operator)
            .with_context(|| format!("key file {}", keys_path.display()))?;
        let session = network::open(
            &NetworkSettings {
                connect: connect.to_vec(),
                listen: Vec::new(),
            },
            &access,
        )
        .await?;
        let k = Keys::new(keys.team());
        let publisher = network::control_publisher(&session, k.operator()).await?;
        let states = session
            .declare_subscriber(k.all_unit_states())
            .await
            .map_err(|e| anyhow::anyhow!("zenoh subscriber: {e}"))?;
        Ok(Console {
            session,
            publisher,
            states,
            validator: Validator::monitor(&keys),
            sealer: keys.sealer(Sender::Operator)?,
            team: keys.team().to_owned(),
            team_size: keys.team_size(),
            seq: 0,
            units: BTreeMap::new(),
        })
    }

    pub fn team_size(&self) -> usize {
        self.team_size
    }

    /// Takes in the units' states for `duration`.
    pub async fn listen(&mut self, duration: Duration) {
        let deadline = tokio::time::Instant::now() + duration;
        while let Ok(Ok(sample)) = tokio::time::timeout_at(deadline, self.states.recv_async()).await
        {
            self.take(&sample.payload().to_bytes());
        }
    }

    /// Takes in whatever states are waiting.
    pub fn poll(&mut self) {
        while let Ok(Some(sample)) = self.states.try_recv() {
            self.take(&sample.payload().to_bytes());
        }
    }

    fn take(&mut self, bytes: &[u8]) {
        let Ok(envelope) = self.validator.receive_frame(bytes, 0) else {
            return;
        };
        if let (Sender::Unit(i), Body::Unit(tick)) = (envelope.sender, envelope.body) {
            self.units.insert(
                i,
                UnitView {
                    tick,
                    stamp_us: envelope.stamp_us,
                    heard: Instant::now(),
                },
            );
        }
    }

    /// The team's clock now, as far as the units' newest stamp tells.
    fn team_now_us(&self) -> Option<u64> {
        self.units
            .values()
            .map(|u| u.stamp_us + u.heard.elapsed().as_micros() as u64)
            .max()
    }

    /// Signs and sends an operator command.
    pub async fn send(&mut self, command: OperatorCommand) -> Result<()> {
        let stamp_us = self.team_now_us().unwrap_or_else(wall_us);
        // Sequence numbers follow the team clock (message.rs's convention), so a later console
        // always sends higher ones than an earlier one did.
        self.seq = self.seq.max(stamp_us).saturating_add(1);
        let envelope = Envelope {
            version: PROTOCOL_VERSION,
            team: self.team.clone(),
            sender: Sender::Operator,
            seq: self.seq,
            stamp_us,
            body: Body::Operator(command),
        };
        let frame = self.sealer.seal(&envelope)?;
        network::put(&self.publisher, &frame).await?;
        Ok(())
    }

    /// Whether every unit of the team has been heard.
    pub fn all_heard(&self) -> bool {
        (0..self.team_size).all(|i| self.units.contains_key(&i))
    }

    pub async fn close(self) {
        let _ = self.session.close().await;
    }
}

/// A new mission number: Unix seconds, so every later start from any console is newer.
pub fn new_mission() -> u32 {
    (wall_us() / 1_000_000).min(u64::from(u32::MAX)) as u32
}

/// Sends a start and waits until every unit left Idle (or `timeout`); returns the mission.
pub async fn start(console: &mut Console, timeout: Duration) -> Result<u32> {
    let mission = new_mission();
    let deadline = Instant::now() + timeout;
    loop {
        console.send(OperatorCommand::Start { mission }).await?;
        console.listen(Duration::from_millis(200)).await;
        let started = console.all_heard()
            && console
                .units
                .values()
                .all(|u| u.tick.phase != Phase::Idle || u.tick.announce.propose.is_some());
        if started {
            return Ok(mission);
        }
        if Instant::now() >= deadline {
            bail!(
                "mission {mission}: the team did not start within {:.0} s (heard {} of {} units)",
                timeout.as_secs_f64(),
                console.units.len(),
                console.team_size()
            );
        }
    }
}

/// `moonhaul mission start|stop|status`.
pub async fn run(command: &str, args: &ConsoleArgs) -> Result<()> {
    if !(args.listen_s.is_finite() && args.listen_s > 0.0 && args.listen_s <= 60.0) {
        bail!("--listen-s {}: must be in (0, 60]", args.listen_s);
    }
    let mut console = Console::open(&args.keys, &args.connect)
        .await
        .with_context(|| format!("connecting to {:?}", args.connect))?;
    console.listen(Duration::from_secs_f64(args.listen_s)).await;
    let result = match command {
        "start" => {
            if console.units.is_empty() {
                bail!(
                    "no unit of team {} answered on {:?}",
                    console.team,
                    args.connect
                );
            }
            let mission = start(&mut console, Duration::from_secs(10)).await?;
            println!("mission {mission} started");
            Ok(())
        }
        "stop" => {
            for _ in 0..5 {
                console.send(OperatorCommand::Stop).await?;
                console.listen(Duration::from_millis(100)).await;
            }
            println!("stop sent to team {}", console.team);
            print_status(&console);
            Ok(())
        }
        _ => {
            print_status(&console);
            Ok(())
        }
    };
    console.close().await;
    result
}

fn print_status(console: &Console) {
    println!("team {} ({} units)", console.team, console.team_size);
    for i in 0..console.team_size {
        match console.units.get(&i) {
            None => println!("  unit {i}: not heard"),
            Some(u) => {
                let stop = u
                    .tick
                    .announce
                    .safety_stop
                    .map_or_else(String::new, |s| format!(", stopped: {s:?}"));
                let pending = u.tick.announce.propose.map_or_else(String::new, |t| {
                    format!(", proposing {} → {}", t.from, t.to)
                });
                let p = &u.tick.state.base_pose;
                println!(
                    "  unit {i}: {}{pending}{stop}; base ({:.3}, {:.3}) m, heard {:.1} s ago",
                    u.tick.phase,
                    p.x_m,
                    p.y_m,
                    u.heard.elapsed().as_secs_f64()
                );
            }
        }
    }
}
