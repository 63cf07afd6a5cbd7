mod booth_cli;
mod decode_cli;
