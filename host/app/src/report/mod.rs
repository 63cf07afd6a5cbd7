//! Reports: figures drawn by [`plot`] (the crate's one plotting stack, `plotters` with an embedded
//! font) and a self-contained HTML document that embeds them.

pub mod figures;
pub mod font;
pub mod html;
pub mod plot;
