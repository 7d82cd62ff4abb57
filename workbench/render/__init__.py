"""Seeing a hypothesis as the sensor would: batched depth rendering of many scenes at once (``depth``), and the
log-likelihood of a rendered scene against the observed depth (``likelihood``)."""
