"""The flight log (MCAP): the topic names the writer and the readers share (``topics``), the
writer (``recorder``, foxglove), the streaming reader (``reader``, mcap) and the log directory's
rotation (``rotation``)."""
