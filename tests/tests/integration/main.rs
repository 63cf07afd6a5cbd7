mod booth_cli;
mod simulate;
mod normals_cli;
