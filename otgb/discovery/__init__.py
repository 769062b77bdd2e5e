"""Missing-effect discovery: locate, name, add and verify what f_p lacks (``otgb discover``)."""
