mod booth_cli;
mod calibrate_cli;
mod decode_cli;
mod mc_cli;
mod mc_validation;
mod normals_cli;
mod rig_hil;
mod simulate;
