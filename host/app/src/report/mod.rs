//! Reports: PNG plots drawn with the `image` crate and a built-in bitmap font, and a
//! self-contained HTML document that embeds them.

pub mod figures;
pub mod font;
pub mod html;
pub mod plot;
