//! The operator console over zenoh: `moonhaul mission start | stop | status`.
//!
//! The console holds the team's key file, so it authenticates what it hears and signs what it
//! says. It has no clock of its own in the team's time base (a simulated mission runs on the
//! world's time): it listens to the units first and stamps its commands with the newest unit
//! stamp it accepted plus the time since it heard it, at most a control period. A start names
//! a mission number that must exceed every earlier one; the console uses the Unix time in
//! seconds, so starts from any console increase. A stop names the mission the units report (so a recording of it never
//! stops a later mission; with no unit heard it names none and must then arrive fresh).
//!
//! **Honest answers.** Every unit reports, in each state message, what it did with the latest
//! operator command ([`moonhaul_coord::message::OperatorAck`]). After sending, `start` and
//! `stop` wait up to `--ack-timeout-s` (resending every half second, each with a new sequence
//! number) for each unit's answer to one of the commands it sent, then print per unit:
//! acknowledged, rejected and why (authentication, wrong mission, already in a mission, …), or
//! silent, and fail unless every unit acknowledged. A console whose key file is not the team's
//! cannot join the team's network at all (zenoh refuses its session before any frame is read),
//! so no unit can answer it: when its session has no peer although an endpoint accepts TCP
//! connections, it reports every unit as having rejected it for authentication.

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use moonhaul_coord::auth::{KeyFile, Sealer};
use moonhaul_coord::message::{
    Body, Envelope, OperatorAck, OperatorCommand, Refusal, Rejection, Sender, StopReason, UnitTick,
    Verdict, PROTOCOL_VERSION,
};
use moonhaul_coord::Validator;
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
    /// `start` and `stop`: how long to wait for every unit's answer, s (in (0, 60]).
    #[arg(long, default_value_t = 5.0, value_name = "S")]
    pub ack_timeout_s: f64,
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
    /// Units heard only in frames that fail authentication under this key file.
    unauthenticated: BTreeSet<usize>,
    connect: Vec<String>,
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
            unauthenticated: BTreeSet::new(),
            connect: connect.to_vec(),
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
        let envelope = match self.validator.receive_frame(bytes, 0) {
            Ok(envelope) => envelope,
            Err(Rejection::BadMac {
                sender: Sender::Unit(i),
            }) => {
                self.unauthenticated.insert(i);
                return;
            }
            Err(_) => return,
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
            .map(|u| extrapolated_stamp_us(u.stamp_us, u.heard.elapsed()))
            .max()
    }

    /// Signs and sends an operator command; returns its sequence number.
    pub async fn send(&mut self, command: OperatorCommand) -> Result<u64> {
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
        Ok(self.seq)
    }

    /// The mission the units report (the newest, should they differ).
    pub fn mission(&self) -> Option<u32> {
        self.units
            .values()
            .filter_map(|u| u.tick.announce.mission)
            .max()
    }

    /// Sends `command` (again every half second, each time with a new sequence number) until
    /// every unit answered one of the copies or `timeout` passed; returns each unit's answer.
    pub async fn command(
        &mut self,
        command: OperatorCommand,
        timeout: Duration,
    ) -> Result<Vec<Answer>> {
        let deadline = Instant::now() + timeout;
        let mut sent = Vec::new();
        loop {
            sent.push(self.send(command).await?);
            let resend = Instant::now() + Duration::from_millis(500);
            while Instant::now() < resend.min(deadline) {
                self.listen(Duration::from_millis(50)).await;
                if self
                    .answers(&sent)
                    .iter()
                    .all(|a| matches!(a, Answer::Acknowledged | Answer::Rejected(_)))
                {
                    return Ok(self.answers(&sent));
                }
            }
            if Instant::now() >= deadline {
                break;
            }
        }
        let mut answers = self.answers(&sent);
        if self.units.is_empty() && self.session.info().peers_zid().await.next().is_none() {
            if let Some(endpoint) = self.connect.iter().find(|e| accepts_tcp(e)) {
                let why = format!(
                    "authentication: {endpoint} accepts connections but the team refused this \
                     console's session (its key file is not the team's)"
                );
                answers.fill(Answer::Rejected(why));
            }
        }
        Ok(answers)
    }

    /// Each unit's answer to one of the commands numbered `sent`.
    fn answers(&self, sent: &[u64]) -> Vec<Answer> {
        (0..self.team_size)
            .map(|i| {
                let Some(u) = self.units.get(&i) else {
                    return match self.unauthenticated.contains(&i) {
                        true => Answer::Rejected(
                            "authentication: its frames fail this key file's check, so it \
                             refuses this console's frames the same way"
                                .into(),
                        ),
                        false => Answer::Silent,
                    };
                };
                match u.tick.announce.operator {
                    Some(OperatorAck {
                        seq: Some(seq),
                        verdict,
                    }) if sent.contains(&seq) => match verdict {
                        Verdict::Accepted => Answer::Acknowledged,
                        Verdict::Rejected(why) => Answer::Rejected(why.to_string()),
                    },
                    Some(OperatorAck {
                        seq: None,
                        verdict: Verdict::Rejected(Refusal::Authentication),
                    }) => Answer::Unanswered(
                        "its latest refused operator frame failed authentication".into(),
                    ),
                    _ => Answer::Unanswered("heard, but it has not answered".into()),
                }
            })
            .collect()
    }

    /// Whether every unit of the team has been heard.
    pub fn all_heard(&self) -> bool {
        (0..self.team_size).all(|i| self.units.contains_key(&i))
    }

    /// The first unit whose newest state announces a safety stop, and its reason. At start-up
    /// each unit stops until it hears its peers, and each then reports the other's stop for
    /// a tick or two: a start sent then is refused ("the team is stopped").
    pub fn first_stopped(&self) -> Option<(usize, StopReason)> {
        self.units
            .iter()
            .find_map(|(i, u)| u.tick.announce.safety_stop.map(|reason| (*i, reason)))
    }

    pub async fn close(self) {
        let _ = self.session.close().await;
    }
}

/// What a unit answered an operator command.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Answer {
    Acknowledged,
    /// Refused, and why.
    Rejected(String),
    /// Its states arrive, but none answers a command this console sent (what it last said).
    Unanswered(String),
    /// Nothing heard from it.
    Silent,
}

impl std::fmt::Display for Answer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Answer::Acknowledged => f.write_str("acknowledged"),
            Answer::Rejected(why) => write!(f, "rejected: {why}"),
            Answer::Unanswered(what) => write!(f, "no answer ({what})"),
            Answer::Silent => f.write_str("silent (not heard)"),
        }
    }
}

/// Whether a `tcp/host:port` endpoint accepts a TCP connection within a second.
fn accepts_tcp(endpoint: &str) -> bool {
    use std::net::ToSocketAddrs as _;
    let Some(addr) = endpoint.strip_prefix("tcp/") else {
        return false;
    };
    let Ok(mut addrs) = addr.to_socket_addrs() else {
        return false;
    };
    addrs.any(|a| std::net::TcpStream::connect_timeout(&a, Duration::from_secs(1)).is_ok())
}

/// Prints each unit's answer to `what`; fails, naming the units, unless every unit
/// acknowledged.
fn report(console: &Console, what: &str, answers: &[Answer]) -> Result<()> {
    println!(
        "{what} (team {}, {} units):",
        console.team, console.team_size
    );
    for (i, a) in answers.iter().enumerate() {
        println!("  unit {i}: {a}");
    }
    all_acknowledged(what, answers)
}

/// Fails, naming each unit that did not acknowledge `what` and its answer.
fn all_acknowledged(what: &str, answers: &[Answer]) -> Result<()> {
    let failed: Vec<String> = answers
        .iter()
        .enumerate()
        .filter(|(_, a)| **a != Answer::Acknowledged)
        .map(|(i, a)| format!("unit {i} {a}"))
        .collect();
    if failed.is_empty() {
        return Ok(());
    }
    bail!(
        "{what}: {} of {} units did not acknowledge: {}",
        failed.len(),
        answers.len(),
        failed.join("; ")
    )
}

/// A new mission number: Unix seconds, so every later start from any console is newer.
pub fn new_mission() -> u32 {
    (wall_us() / 1_000_000).min(u64::from(u32::MAX)) as u32
}

/// Sends a start of a new mission and waits (at most `timeout`) until every unit answered it;
/// fails, naming each unit's answer, unless every unit acknowledged. Returns the mission.
pub async fn start(console: &mut Console, timeout: Duration) -> Result<u32> {
    let mission = new_mission();
    let answers = console
        .command(OperatorCommand::Start { mission }, timeout)
        .await?;
    all_acknowledged(&format!("start of mission {mission}"), &answers)?;
    Ok(mission)
}

/// The longest the console carries a unit's stamp forward by its own wall clock: about a
/// control period. Units publish every tick, so a live team's newest stamp is never much older
/// in real time; a lockstep world's clock runs slower than the wall whenever the machine is
/// loaded, and carrying the stamp forward by the wall time since it was heard then put a start
/// more than the staleness bound (3 periods) ahead of a unit's clock: refused as from the
/// future, the team never started.
const MAX_EXTRAPOLATION: Duration = Duration::from_millis(20);

/// A unit's stamp `stamp_us`, heard `since` ago, carried forward to now (at most
/// [`MAX_EXTRAPOLATION`]).
fn extrapolated_stamp_us(stamp_us: u64, since: Duration) -> u64 {
    stamp_us.saturating_add(since.min(MAX_EXTRAPOLATION).as_micros() as u64)
}

/// `moonhaul mission start|stop|status`.
pub async fn run(command: &str, args: &ConsoleArgs) -> Result<()> {
    if !(args.listen_s.is_finite() && args.listen_s > 0.0 && args.listen_s <= 60.0) {
        bail!("--listen-s {}: must be in (0, 60]", args.listen_s);
    }
    if !(args.ack_timeout_s.is_finite() && args.ack_timeout_s > 0.0 && args.ack_timeout_s <= 60.0) {
        bail!("--ack-timeout-s {}: must be in (0, 60]", args.ack_timeout_s);
    }
    let ack_timeout = Duration::from_secs_f64(args.ack_timeout_s);
    let mut console = Console::open(&args.keys, &args.connect)
        .await
        .with_context(|| format!("connecting to {:?}", args.connect))?;
    console.listen(Duration::from_secs_f64(args.listen_s)).await;
    let result = match command {
        "start" => {
            let mission = new_mission();
            let answers = console
                .command(OperatorCommand::Start { mission }, ack_timeout)
                .await?;
            report(&console, &format!("start of mission {mission}"), &answers)
                .map(|()| println!("mission {mission} started"))
        }
        "stop" => {
            let mission = console.mission();
            let answers = console
                .command(OperatorCommand::Stop { mission }, ack_timeout)
                .await?;
            let what = match mission {
                Some(m) => format!("stop of mission {m}"),
                None => "stop (no unit reported a mission)".to_owned(),
            };
            let result = report(&console, &what, &answers);
            print_status(&console);
            result
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stamp_is_carried_forward_by_at_most_a_control_period() {
        assert_eq!(
            extrapolated_stamp_us(1_000, Duration::from_micros(5)),
            1_005
        );
        let cap = MAX_EXTRAPOLATION.as_micros() as u64;
        assert_eq!(
            extrapolated_stamp_us(1_000, Duration::from_secs(3)),
            1_000 + cap
        );
        assert_eq!(
            extrapolated_stamp_us(u64::MAX, Duration::from_secs(1)),
            u64::MAX
        );
    }
}
