//! Cost of one full control cycle of a unit on the virtual bus: 9 RPDOs and a SYNC out, 18
//! TPDOs (statusword + position, velocity + torque) in and decoded, plus stepping the nine
//! emulated drives through the SYNC period. Prints figures; asserts no timings.

use std::error::Error;
use std::hint::black_box;
use std::time::Instant;

use moonhaul_hal::can::{Cia402Master, UnitCanConfig, VirtualBus};
use moonhaul_hal::{ArmDrive, Drive, WheelDrive};

const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/unit_can.toml");
const CYCLES: u32 = 20_000;

fn main() -> Result<(), Box<dyn Error>> {
    let mut config = UnitCanConfig::from_file(CONFIG)?;
    // The emulator's clock step sets how much drive simulation each cycle includes; a step of
    // one period leaves the master's own cost.
    for step_s in [0.001, config.sync_period_s] {
        config.emulator.step_s = step_s;
        let mut master = Cia402Master::new(VirtualBus::for_unit(&config), &config);
        master.enable()?;
        let before = master.stats();
        let start = Instant::now();
        for k in 0..CYCLES {
            let t = f64::from(k) * config.sync_period_s;
            master.command_velocity(&[t.sin(), t.cos()])?;
            master.command_position(&[0.1 * t.sin(); 7])?;
            master.sync()?;
            black_box(master.read_arm()?);
        }
        let per_cycle = start.elapsed() / CYCLES;
        let after = master.stats();
        let frames = (after.frames_sent - before.frames_sent)
            + (after.frames_received - before.frames_received);
        println!(
            "control cycle, emulator step {:.0} ms: {per_cycle:?} per cycle = {:.0} cycles/s, {:.1} frames/cycle, {:.3}% of the {:.0} ms period",
            step_s * 1e3,
            1.0 / per_cycle.as_secs_f64(),
            frames as f64 / f64::from(CYCLES),
            100.0 * per_cycle.as_secs_f64() / config.sync_period_s,
            config.sync_period_s * 1e3,
        );
    }
    Ok(())
}
