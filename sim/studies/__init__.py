"""Studies behind `toptag eval ...`: each module has run(...) -> dict and main(argv) -> int."""
