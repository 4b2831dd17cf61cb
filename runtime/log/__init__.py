"""The flight log: MCAP topic names (``topics``), shared by the writer and the reader."""
