//! The Monte Carlo options shared by every command that simulates (`simulate`, `demo`, `bench`).

use std::path::PathBuf;

use mlsss::virtual_booth::{ResponseCache, SimulationOptions};

#[derive(Debug, Clone, clap::Args)]
pub struct MonteCarloArgs {
    /// Photons per Monte Carlo skin response (per material, angle and channel); default: the
    /// simulator's for the booth size.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub photons: Option<u64>,
    /// Monte Carlo response cache folder (default: $MLSSS_CACHE, else $XDG_CACHE_HOME/mlsss,
    /// else ~/.cache/mlsss).
    #[arg(long, value_name = "DIR")]
    pub cache: Option<PathBuf>,
}

impl MonteCarloArgs {
    /// Overrides the simulator's defaults with the options given.
    pub fn apply(&self, opts: &mut SimulationOptions) {
        if let Some(photons) = self.photons {
            opts.mc.photons = photons;
        }
        if let Some(dir) = &self.cache {
            opts.cache = ResponseCache::new(dir);
        }
    }
}
