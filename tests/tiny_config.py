"""The tiny synthetic scene's pipeline.yaml used by the end-to-end CLI tests (numbers are
meaningless at this size; it exercises every stage in seconds)."""

TINY_CONFIG = """
    workspace: ws
    executor: {kind: local, workers: 1}
    scenes:
      tiny:
        synthetic:
          preset: demo
          seed: 3
          overrides: {n_frames: 8, n_people: 1, motions: [[run]],
                      rig: {n_cameras: 3, width: 192, height: 144}, board: {n_frames: 12}}
    stages:
      synth: {}
      calibrate: {needs: [synth], params: {synthetic_source: rig}}
      extract: {needs: [calibrate], params: {crop_size: 128, association_method: hull}}  # fast
      pretrain: {params: {gaussian_steps: 2, batch_size: 2, worlds: 2, world_cameras: 3,
                          world_frames: 3, world_people: 1, lift_steps: 20}}
      fuse: {needs: [extract]}
      train: {needs: [extract, pretrain, fuse], params: {steps: 2, batch_size: 2, num_targets: 2}}
"""
