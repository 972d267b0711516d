"""Trainer daemon for the Refiner, Estimator and Tabulator (consumer half of cuboid-fit)."""
