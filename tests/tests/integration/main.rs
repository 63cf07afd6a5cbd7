mod booth_cli;
mod normals_cli;
mod rig_hil;
