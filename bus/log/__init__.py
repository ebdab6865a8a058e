"""Episode logs: the MCAP writer (``writer``), the recorder that fills it from the bus
(``record``), and the defensive reader (``reader``, over ``mcap_scan``)."""
