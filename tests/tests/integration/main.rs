mod booth_cli;
mod rig_hil;
