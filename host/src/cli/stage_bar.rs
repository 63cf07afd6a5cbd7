//! The simulator's stages (`virtual_booth::Progress`) shown as one indicatif bar on stderr,
//! relabelled per stage; shared by `mlsss simulate` and `mlsss demo`.

use indicatif::ProgressBar;
use mlsss::virtual_booth::Progress;

pub struct Bar(pub ProgressBar);

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
