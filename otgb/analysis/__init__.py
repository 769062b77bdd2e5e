"""Analysis that needs no training loop: the grey-box's component analysis and the comparison figures, used by the
callbacks and by ``otgb discover``."""
