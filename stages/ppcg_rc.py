"""Stage: ppcg_rc (library call + artifact I/O). Filled in by its issue."""
