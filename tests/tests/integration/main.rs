mod booth_cli;
mod mc_cli;
mod mc_validation;
mod simulate;
mod decode_cli;
mod calibrate_cli;
mod normals_cli;
mod rig_hil;
