mod booth_cli;
mod calibrate_cli;
mod normals_cli;
