"""``cdmp demo``: the project's main demonstration.

Today it runs the toy reproduction of paper 000 (section IV-A) and prints its table; the full
node-graph demo (learn, stream to the simulated robot, obstacle and goal changes, bag) replaces
it when the ROS node graph lands.
"""
import argparse

NAME = 'demo'
HELP = 'run the demo (today: the DMP vs CDMP toy reproduction of paper 000 IV-A)'


def add_arguments(parser):
    parser.add_argument('--out', default='out/demo', help='output directory (default out/demo)')


def run(args):
    from cdmp_ros.experiments import exp_toy
    return exp_toy.run(argparse.Namespace(out=args.out, no_plot=False))
