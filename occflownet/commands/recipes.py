"""`occflownet recipes`: the named training recipes (``occflownet/train/recipes.py``): what each supervises, what a
``tiny`` step of it costs on this machine (the reference machine's measured seconds scaled by the two machines'
float32 matmul rates), what it scored and where that is measured."""
import argparse

HELP = "list the named training recipes: what each supervises, its step cost here, its measured figure"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--names", action="store_true", help="only the names, one per line")


def run(args) -> int:
    from occflownet.train.recipes import DEFAULT_RECIPE, RECIPES

    if args.names:
        print("\n".join(RECIPES))
        return 0
    from occflownet.quickstart import matmul_gflops
    from occflownet.train.recipes import REFERENCE_GFLOPS

    gflops = matmul_gflops()
    print(f"tiny step seconds on this machine: the reference machine's, scaled by float32 matmul {gflops:.0f} "
          f"against {REFERENCE_GFLOPS:.0f} GFLOP/s\n")
    print("| recipe | supervises | s / tiny step here | measured | where |\n|---|---|---|---|---|")
    for r in RECIPES.values():
        cost = "not measured" if r.step_seconds is None else f"{r.step_seconds * REFERENCE_GFLOPS / gflops:.2f}"
        name = f"**{r.name}** (default)" if r.name == DEFAULT_RECIPE else r.name
        print(f"| {name} | {r.supervises} | {cost} | {r.measured or 'not measured as spelled'} | {r.source} |")
    print("\n" + "\n".join(f"{r.name}: {r.description}" for r in RECIPES.values()))
    return 0
