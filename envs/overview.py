"""``python -m envs.overview``: print the overview table of docs/environments.md, made from the
registered tasks' declarations (:func:`envs.task.overview_table`); a test checks that the page
holds it."""

from envs.task import overview_table

if __name__ == "__main__":
    import envs  # noqa: F401  (registers the shipped tasks)

    print(overview_table(), end="")
