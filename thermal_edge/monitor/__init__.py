"""The operator's live view of a running service (``thermal-edge monitor``): a snapshot read from
the metrics endpoint or from the CAN bus (:mod:`.snapshot`), drawn as text (:mod:`.view`)."""
