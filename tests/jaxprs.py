"""Walking traced programs, for tests that assert what a program is made of."""

import jax
import jax.extend.core


def equations(jaxpr):
    """Every equation of ``jaxpr`` and of the jaxprs in its equations' parameters (loop bodies,
    branches, inner jits), depth first."""
    for eqn in jaxpr.eqns:
        yield eqn
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            yield from equations(sub)


def scatters_that_may_repeat_an_index(jaxpr) -> list[str]:
    """Where each scatter of ``jaxpr`` without ``unique_indices`` comes from (the innermost frame
    outside JAX, or the equation's name stack). XLA's deterministic GPU options rewrite such a
    scatter into a form that sorts its indices."""
    found = []
    for eqn in equations(jaxpr):
        if eqn.primitive.name.startswith("scatter") and not eqn.params.get("unique_indices", False):
            found.append(_origin(eqn))
    return found


def _origin(eqn) -> str:
    try:
        from jax._src import source_info_util  # noqa: PLC0415 (private: only to name a failure's place)

        frame = source_info_util.user_frame(eqn.source_info.traceback)
        if frame is not None:
            return f"{frame.file_name}:{frame.start_line}"
    except Exception:  # noqa: BLE001 (a name for the message only)
        pass
    return f"{eqn.primitive.name} at {eqn.source_info.name_stack}"
