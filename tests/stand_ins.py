"""Shared by the tests whose fe is a stand-in (tests/test_solve_ahead.py, tests/test_model_mesh_finish.py): which
models' replays are solved, and in which batches, as `twin.analysis.residual.Base.prefetch` would solve them."""

from twin.analysis.predict import TwinModel


class SolvedModels:
    """The models solved so far (`solved`: their keys; the base model's from the start) and the batches that solved
    them (`batches`: a set of keys each)."""

    def __init__(self, *already: TwinModel) -> None:
        self.solved: set = {m.key() for m in already}
        self.batches: list[set] = []

    def prefetch(self, predictor: object, models: list[TwinModel]) -> int:
        """Solve the models not solved yet as one batch; how many."""
        new = {m.key() for m in models} - self.solved
        if new:
            self.batches.append(new)
            self.solved |= new
        return len(new)
