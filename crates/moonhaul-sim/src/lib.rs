//! # moonhaul-sim
//!
//! The training and test world: two wheel–arm units and a shared payload on randomized
//! lunar-analog terrain. Grows into the rapier3d scene and batched environments; it starts
//! with the terrain model of the paper's domain randomization.

pub mod terrain;
