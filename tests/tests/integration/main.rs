mod booth_cli;
mod calibrate_cli;
