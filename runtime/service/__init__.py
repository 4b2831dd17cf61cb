"""Process plumbing of the flight programs: systemd notification (``sdnotify``), stop signals
(``signals``), waits a stop always reaches and closing native resources without hanging (``shutdown``), CPU pinning
(``affinity``) and the output-directory check (``paths``)."""
