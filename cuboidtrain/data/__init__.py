"""The data floor: from the spool to a batch on the training device (paper 3.3.2).

Between the fit (whose framing it reuses, so the networks train as `infer` frames a mask) and
the trainer and eval, which read its batches. One room a stage:

  sampler.py         the epoch's order of names and where the loader stands in it (EpochSampler)
  loader.py          names -> a LoaderBatch: samples read (shared.sample decodes), skipped and
                     counted, collated with their masks still packed (SpoolBatches, make_loader)
  reframing.py       a sample framed at the model's size as `infer` frames a mask (the building,
                     its Framing, its keypoints in the model's px)
  device_framing.py  the batch's masks unpacked and framed on the device (frame_masks)
  prepare.py         a LoaderBatch -> the paper's ChainBatch (x1, x2, x3, x4, ratios)
  freshness.py       how old and how often used a batch's samples are
  census.py          the spool as the trainer's dashboard shows it
"""
