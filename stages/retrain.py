"""Stage: retrain (library call + artifact I/O). Filled in by its issue."""
