//! The simulator's stages (`virtual_booth::Progress`) shown as one indicatif bar on stderr,
//! relabelled per stage; shared by `mlsss simulate` and `mlsss demo`.

use std::time::Duration;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use mlsss::virtual_booth::Progress;

pub struct Bar(pub ProgressBar);

impl Bar {
    /// A bar on stderr that ticks on its own (stages can be long between updates).
    pub fn on_stderr() -> anyhow::Result<Self> {
        let bar = ProgressBar::new(1);
        bar.set_style(
            ProgressStyle::with_template("{msg:32} [{bar:40}] {pos}/{len} {elapsed_precise}")
                .context("progress bar template")?
                .progress_chars("=> "),
        );
        bar.enable_steady_tick(Duration::from_millis(200));
        Ok(Self(bar))
    }

    pub fn finish_and_clear(&self) {
        self.0.finish_and_clear();
    }
}

impl Progress for Bar {
    fn stage(&self, name: &str, total: u64) {
        self.0.set_length(total);
        self.0.set_position(0);
        self.0.set_message(name.to_owned());
    }

    fn advance(&self, n: u64) {
        self.0.inc(n);
    }
}
