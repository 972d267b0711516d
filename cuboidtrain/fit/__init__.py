"""Fitting masks: options, the Fitter, the chain R^K -> S -> T, scoring, masks, keypoints, explanations, export."""
