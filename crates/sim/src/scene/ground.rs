//! The ground: the terrain heightfield collider and height queries against it.

use rand_chacha::ChaCha8Rng;
use rapier3d::parry::shape::HeightField;
use rapier3d::parry::utils::Array2;
use rapier3d::prelude::*;

use crate::config::SimConfig;
use crate::SimError;

pub(super) fn ground_height(world: &PhysicsWorld, ground: ColliderHandle, x: f64, y: f64) -> f64 {
    let collider = &world.colliders[ground];
    let ray = Ray::new(
        Vector::new(x as f32, y as f32, 10.0),
        Vector::new(0.0, 0.0, -1.0),
    );
    collider
        .shape()
        .cast_ray(collider.position(), &ray, 20.0, true)
        .map_or(0.0, |toi| 10.0 - toi as f64)
}

/// The ground: a heightfield (flat when `terrain` is `None`). parry's heightfields are Y-up
/// with rows along local z; the collider is turned by +90° about X so heights point along
/// world Z, which maps local z to world −Y: terrain rows (along +Y) are stored in reverse.
pub(super) fn terrain_collider(
    config: &SimConfig,
    terrain: Option<&crate::terrain::TerrainRandomization>,
    rng: &mut ChaCha8Rng,
) -> Result<ColliderBuilder, SimError> {
    let s = &config.scene;
    let cells = (s.terrain_size_m / s.terrain_spacing_m).round() as usize + 1;
    let heights = match terrain {
        Some(t) => {
            t.sample(cells, s.terrain_spacing_m, rng)
                .map_err(|e| SimError::Config {
                    field: "randomization.terrain",
                    reason: e.to_string(),
                })?
                .heights_m
        }
        None => vec![0.0; cells * cells],
    };
    let mut data = vec![0.0f32; cells * cells];
    for row in 0..cells {
        for col in 0..cells {
            data[(cells - 1 - row) + col * cells] = heights[row * cells + col] as f32;
        }
    }
    let extent = ((cells - 1) as f64 * s.terrain_spacing_m) as f32;
    let shape = HeightField::new(
        Array2::new(cells, cells, data),
        Vector::new(extent, 1.0, extent),
    );
    let pose = Pose::from_parts(
        Vector::new(s.terrain_center_x_m as f32, 0.0, 0.0),
        Rotation::from_rotation_x(std::f32::consts::FRAC_PI_2),
    );
    Ok(ColliderBuilder::new(SharedShape::new(shape))
        .position(pose)
        .friction(1.0)
        .friction_combine_rule(CoefficientCombineRule::Min))
}
