mod booth_cli;
