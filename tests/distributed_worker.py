"""One rank of the distributed training tests (tests/test_distributed.py), started by ``mlx.launch``.

    python tests/distributed_worker.py MODE OUT_DIR [RUN ...]

MODE 'train': the frozen runs of tests/data/make_train_frozen.py (RUN names, default all) at batch
size 2; each rank saves its parameters to OUT_DIR/rank{r}.npz. 'die': rank 1 exits after step 7 of a run that
checkpoints every 5 steps into OUT_DIR. 'mismatch': rank 1 has a different setting. A rank
that fails writes its error to OUT_DIR/rank{r}.err.
"""

import os
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "data"))
sys.path.insert(0, str(HERE.parent))


def main(mode: str, out: Path, runs=()) -> None:
    import numpy as np

    import make_train_frozen as frozen
    from mlx3d.training.distributed import init

    ranks = init("ring")
    r = ranks.rank
    try:
        with tempfile.TemporaryDirectory() as tmp:
            if mode == "train":
                saved = {}
                for name in runs or frozen.RUNS:
                    folder = Path(tmp) / name
                    folder.mkdir()
                    params, trainer = frozen.run(name, folder, ranks=ranks, batch_size=2)
                    saved.update({f"{name}/{k}": v for k, v in params.items()})
                    saved[f"{name}/bytes"] = np.array(ranks.bytes_sent)
                np.savez(out / f"rank{r}.npz", **saved)
            elif mode == "die":
                def progress(done, total, info):
                    if r == 1 and done == 7:
                        os._exit(3)
                frozen.run("vanilla", Path(tmp), ranks=ranks, progress=progress, batch_size=2, checkpoint_every=5, checkpoint_dir=str(out))
            elif mode == "mismatch":
                frozen.run("vanilla", Path(tmp), ranks=ranks, batch_size=2, lambda_dssim=0.2 + 0.1 * r)
    except Exception as exc:
        (out / f"rank{r}.err").write_text(f"{type(exc).__name__}: {exc}")
        raise


if __name__ == "__main__":
    main(sys.argv[1], Path(sys.argv[2]), sys.argv[3:])
