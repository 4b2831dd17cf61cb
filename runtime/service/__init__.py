"""Process plumbing of the flight programs: systemd notification (``sdnotify``), stop signals
(``signals``), closing native resources without hanging (``shutdown``), CPU pinning
(``affinity``) and the output-directory check (``paths``)."""
