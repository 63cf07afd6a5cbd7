mod booth_cli;
mod simulate;
