"""The paper's experiments, reproduced: the report (Table 3, Figure 14, occlusion, refinement,
extractors, shape selection), the localization experiment (section 5) and their figures.

These are the only modules under `cuboidtrain/` that may draw samples with the generator
(`cuboidgen`): the library that fits masks never does (tests/test_layout.py holds that).
"""
