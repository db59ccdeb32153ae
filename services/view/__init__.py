"""`toptag view`: the live view of an intersection in the browser (Rerun's web viewer).

site: the static map (roads, RSUs, their view footprints) from the site files; rerun_server: the
bundled Rerun binary, started on loopback and stopped by its PID; app: what the view subscribes to and
draws, and the command."""
