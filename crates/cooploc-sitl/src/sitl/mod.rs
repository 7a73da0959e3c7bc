//! The simulated world: truth trajectories of land vehicles, their sensors' error models, and
//! the scenario files that hold every number. No networking, no filters, no clocks: a run is a
//! pure function of `(scenario, seed, run index)`, and it produces the same sample types
//! ([`ImuSample`](crate::estimation::ImuSample), [`OdometerSample`](crate::estimation::OdometerSample),
//! [`RangeSample`](crate::estimation::RangeSample)) that the MAVLink layer decodes and the filters
//! consume.
//!
//! | module | what |
//! |---|---|
//! | [`scenario`] | the TOML scenario: world, sensors, ranging schedules, platforms, initial sigmas, filter tuning; validation naming the bad field |
//! | [`truth`] | the world model (flat Earth, NED, constant gravity, Earth rate), truth trajectories, exact IMU increments |
//! | [`sensors`] | IMU, odometer and ranging error models, seeded per platform, sensor and run |
//! | [`world`] | a scenario made into a world: a run's inputs as vectors or as one time-ordered event stream; initial estimates |
//!
//! The world in one paragraph: a local NED tangent plane fixed to the Earth at the scenario
//! latitude, flat, with constant gravity `[0, 0, g]` and Earth rate
//! `7.292115e-5 [cos L, 0, -sin L]` rad/s; body axes FRD; vehicles on level ground (roll = pitch =
//! 0, constant D) that never slip, each following segments of constant longitudinal acceleration
//! and yaw rate. The INS mechanises the same model, so with perfect sensors it reproduces the
//! truth (see the strapdown test in [`truth`]).
//!
//! ```
//! use cooploc_sitl::sitl::{Scenario, World, PAPER_TOML};
//! let world = World::new(&Scenario::from_toml_str(PAPER_TOML).unwrap()).unwrap();
//! let run = world.run_inputs(1, 0);
//! assert_eq!(run.platforms.len(), 3);
//! let ranges = world.ranges("four-events", 1, 0).unwrap();
//! assert_eq!(ranges.len(), 4);
//! ```

pub mod scenario;
pub mod sensors;
pub mod truth;
pub mod world;

pub use scenario::{ASYNC_TOML, MIXED_TOML, PAPER_TOML, Scenario, ScenarioError};
pub use sensors::{SensorErrors, SensorModel};
pub use truth::{Earth, Trajectory, TruthState};
pub use world::{InitialEstimate, PlatformRun, RunInputs, SimEvent, SimEvents, World};
