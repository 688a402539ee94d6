"""Stage: ptsn_sweep (library call + artifact I/O). Filled in by its issue."""
