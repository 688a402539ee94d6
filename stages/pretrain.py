"""Stage: pretrain (library call + artifact I/O). Filled in by its issue."""
