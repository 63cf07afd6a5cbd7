mod booth_cli;
mod decode_cli;
mod normals_cli;
