"""The runtime's programs: ``fly`` (``cmnav fly``, the field program systemd runs), ``sitl``
(``python -m runtime.programs.sitl``, the runtime's side of ``cmnav sitl``), ``replay`` (``cmnav
replay``), the one dry-run ``episode`` script both flight programs fly, and ``stop`` (the safe stop
on SIGTERM / SIGINT in every phase)."""
