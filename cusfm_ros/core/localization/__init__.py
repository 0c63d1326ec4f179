"""Localization against a prior map: the map model, absolute pose and the localizer."""
