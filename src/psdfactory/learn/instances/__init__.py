"""The instance estimator (architecture name ``instances``): segment every particle, measure
it, then read the PSD off the measured particles.

- **Network** (`InstanceNet`): a torchvision ResNet-18 trunk cut after ``layer2`` (stride 8;
  ``train.instances.trunk_stages: 3``: after ``layer3``, stride 16, with a decoder stage more at stride 8;
  ImageNet weights with ``train.pretrained`` as for the CNNs) and a light U-Net decoder with skips
  at strides 4, 2 and 1, predicting four maps (MAPS) at the input's resolution, any size: a
  foreground logit, a boundary logit, a logit of the normalised distance to the instance's
  boundary and a logit of the size map.
- **Targets** from ``mask.png`` (`instance_targets`): foreground = mask > 0; boundary = instance
  pixels with a 4-neighbour of another id (the background included); distance = each
  instance's own Euclidean distance transform divided by its maximum (1 at its centre, so a
  3-px grain and a 30-px one get seeds alike); size (`size_target`) = the true sieve size in
  pixels of the particle a pixel belongs to, from the particle manifest, log-encoded in [0, 1]
  — however much of the particle is hidden, so the network learns to see a whole grain in a
  part of it, and a merged or split instance still reads its grains' sizes.
- **Loss** (`instance_loss`): BCE(foreground) + BCE(boundary, positive-weighted by the
  background / boundary ratio of the training masks) + L1(distance) + L1(log2 size, in octaves)
  on foreground pixels.
- **Training** on random crops of the training split (``train.input_size.instances`` px) with
  flips / 90° rotations applied to image and targets alike and the photometric jitter of
  `augment.photometric` on the image (it changes no target); model selection by validation
  loss on the full validation images. Then, with the best weights: the post-processing
  settings (thresholds, h-maxima depth, seed merging) are picked by F1 at IoU 0.5 against the
  validation masks, and a ridge read-out from `particles.instance_stats` to the labels is fitted
  on the training and validation scenes' *predicted* instances (the camera cannot see hidden
  fines; the read-out learns what they add), reading the statistics ``train.instances.readout``
  names (READOUTS: the footprints', with ``footprints+size_map`` the size map's too, with
  ``footprints+size_map_d10_d50`` the size map's for d10 and d50 only). All of
  it is stored as plain lists in the model file's meta.
- **Inference** (`InstanceEstimator`): full image → maps (with ``train.instances.tta``
  averaged over views of the image — its quarter turns and mirror images, each turned back,
  `averaged_maps`; off by default) → `split_instances` → `measure_instances`
  at the image's mm per pixel (sieve size per ``train.instances.sieve_method``: by default the
  footprint's min Feret diameter; ``size_map``, the size map's median over the instance, reads
  partly hidden grains whole but misreads the fines and transfers worse to Cycles renders —
  measured in docs/experiments.md) → raw number-weighted d10/d50/d90 of the instances not touching
  the image edge (`psd_from_instances`) and the calibrated d10/d50/d90 (the read-out; sorted so
  that d10 ≤ d50 ≤ d90).

The package, by job (torch-free modules first: the ceiling job and the scene side's checks use
them without PyTorch):

- `measure`: per-grain measurements of an instance mask, the sieve-size estimates;
- `watershed`: from the network's maps to an instance mask;
- `stats`: from measured grains to the PSD and the read-out's per-image statistics;
- `scoring`: a predicted mask against the true one (matching, P/R/F1, size errors);
- `draw`: overlays and masks for a person;
- `targets`: the training targets of a mask, the loss, crops of image and targets together;
- `net`: the network;
- `estimator`: `InstanceEstimator`, the `learn.estimator.Estimator` that runs it all;
- `training`: its training (the shared `learn.fit` loop), post-processing choice and read-out fit.
"""

ARCH = "instances"
