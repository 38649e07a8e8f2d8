//! Simulation: meshes ([`mesh`]), the energies of the incremental potential ([`energy`]),
//! scene files ([`scene`]), the implicit time stepper and its Newton loop
//! ([`integrator`]), the Newton loop's device operators ([`device`]), the `run` driver
//! with its output files ([`driver`]), and the fallible scene-sized allocations
//! ([`memory`]).

pub mod checkpoint;
pub mod device;
pub mod driver;
pub mod energy;
pub mod integrator;
pub mod memory;
pub mod mesh;
mod output;
pub mod phases;
mod resume;
mod run_error;
mod run_options;
pub mod scene;
mod scene_setup;
mod summary;
mod time_loop;
