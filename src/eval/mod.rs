//! Data side of `moonhaul eval`: one evaluation episode as a CSV of samples ([`episode`]) and
//! the paper's per-phase simulation metrics computed from those samples ([`metrics`]). Both
//! are pure functions of the rows, so anyone can recompute the reported figures from the CSVs;
//! [`rollout`] produces the rows by running policies and the scripted baseline in the simulator,
//! [`deployed`] by flying whole missions through the onboard tick; [`progress`] says on stderr
//! how far a run is.

pub mod deployed;
pub mod episode;
pub mod metrics;
pub mod plot;
pub mod progress;
pub mod rollout;
