mod booth_cli;
mod normals_cli;
