"""Stage: ppcg_cf (library call + artifact I/O). Filled in by its issue."""
