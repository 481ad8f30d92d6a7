"""Model discovery: the campaign (``pipeline``), its statistics from the cells to the verdict
(``verdict``: the discrepancy test, the scores, the rules that name a cause), pooled DEM replicate
noise (``replicate_noise``), the report (``report``). The candidate mechanisms live with the model,
in ``torchdem.mechanisms``."""
