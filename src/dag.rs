//! The stage graph (petgraph): topological order, cycle reports that name the cycle, and the
//! `--until` / `--only` selection of what a run must bring up to date.

use std::collections::BTreeSet;

use petgraph::{algo, graph::DiGraph, graph::NodeIndex, Direction};

use crate::config::{ConfigError, Pipeline};

/// The pipeline's dependency graph; node weights are indices into `Pipeline::stages`.
pub struct Dag {
    graph: DiGraph<usize, ()>,
    /// Stage indices in a topological order (ties broken by file order).
    pub order: Vec<usize>,
}

impl Dag {
    /// Builds the graph; a cycle is a configuration error naming it (`a -> b -> a`).
    pub fn build(p: &Pipeline) -> Result<Dag, ConfigError> {
        let mut graph = DiGraph::new();
        let nodes: Vec<NodeIndex> = (0..p.stages.len()).map(|i| graph.add_node(i)).collect();
        for (i, s) in p.stages.iter().enumerate() {
            for up in s.upstream_names() {
                let u = p.index_of(up).expect("inputs validated");
                graph.add_edge(nodes[u], nodes[i], ());
            }
        }
        if let Some(cycle) = find_cycle(&graph) {
            let names: Vec<&str> = cycle.iter().map(|&i| p.stages[i].name.as_str()).collect();
            let first = &p.stages[cycle[0]];
            return Err(ConfigError {
                file: p.file.clone(),
                loc: first.loc.clone(),
                stage: Some(first.name.clone()),
                key: Some("inputs".into()),
                message: format!(
                    "the inputs form a cycle: {} -> {}",
                    names.join(" -> "),
                    names[0]
                ),
            });
        }
        // Kahn's algorithm, always taking the earliest stage in file order that is ready.
        let mut indeg: Vec<usize> = nodes
            .iter()
            .map(|&n| graph.neighbors_directed(n, Direction::Incoming).count())
            .collect();
        let mut ready: BTreeSet<usize> = (0..nodes.len()).filter(|&i| indeg[i] == 0).collect();
        let mut order = Vec::with_capacity(nodes.len());
        while let Some(i) = ready.pop_first() {
            order.push(i);
            for d in graph.neighbors_directed(nodes[i], Direction::Outgoing) {
                let d = graph[d];
                indeg[d] -= 1;
                if indeg[d] == 0 {
                    ready.insert(d);
                }
            }
        }
        Ok(Dag { graph, order })
    }

    /// Direct upstream stages of stage `i`.
    pub fn upstream(&self, i: usize) -> Vec<usize> {
        self.graph
            .neighbors_directed(NodeIndex::new(i), Direction::Incoming)
            .map(|n| self.graph[n])
            .collect()
    }

    /// Direct downstream stages of stage `i`.
    pub fn downstream(&self, i: usize) -> Vec<usize> {
        self.graph
            .neighbors_directed(NodeIndex::new(i), Direction::Outgoing)
            .map(|n| self.graph[n])
            .collect()
    }

    /// Stage `i` and everything it depends on.
    pub fn ancestors_and_self(&self, i: usize) -> BTreeSet<usize> {
        let mut seen = BTreeSet::from([i]);
        let mut stack = vec![i];
        while let Some(n) = stack.pop() {
            for u in self.upstream(n) {
                if seen.insert(u) {
                    stack.push(u);
                }
            }
        }
        seen
    }

    /// Stage `i` and everything that depends on it.
    pub fn descendants_and_self(&self, i: usize) -> BTreeSet<usize> {
        let mut seen = BTreeSet::from([i]);
        let mut stack = vec![i];
        while let Some(n) = stack.pop() {
            for d in self.downstream(n) {
                if seen.insert(d) {
                    stack.push(d);
                }
            }
        }
        seen
    }

    /// Graphviz text of the graph.
    pub fn dot(&self, p: &Pipeline) -> String {
        let mut s = String::from("digraph pipeline {\n  rankdir=LR;\n  node [shape=box];\n");
        for &i in &self.order {
            let st = &p.stages[i];
            s.push_str(&format!(
                "  \"{}\" [label=\"{}\\n({})\"];\n",
                st.name,
                st.name,
                st.kind.kind()
            ));
        }
        for &i in &self.order {
            let st = &p.stages[i];
            let gathered = st
                .gather
                .iter()
                .flat_map(|(slot, ups)| ups.iter().map(move |(_, up)| (slot, up)));
            for (slot, up) in st.inputs.iter().chain(gathered) {
                s.push_str(&format!(
                    "  \"{up}\" -> \"{}\" [label=\"{slot}\"];\n",
                    st.name
                ));
            }
        }
        s.push_str("}\n");
        s
    }
}

/// One cycle of the graph as node weights in edge order, if there is one.
fn find_cycle(g: &DiGraph<usize, ()>) -> Option<Vec<usize>> {
    for scc in algo::tarjan_scc(g) {
        let self_loop = scc.len() == 1 && g.contains_edge(scc[0], scc[0]);
        if scc.len() < 2 && !self_loop {
            continue;
        }
        // Walk edges inside the component from its first node until we come back.
        let inside: BTreeSet<NodeIndex> = scc.iter().copied().collect();
        let start = *scc.iter().min_by_key(|n| g[**n]).unwrap();
        let mut path = vec![start];
        let mut seen = BTreeSet::from([start]);
        let mut cur = start;
        loop {
            let next = g
                .neighbors_directed(cur, Direction::Outgoing)
                .filter(|n| inside.contains(n))
                .min_by_key(|n| (*n != start, g[*n]))
                .unwrap();
            if next == start {
                return Some(path.iter().map(|n| g[*n]).collect());
            }
            if !seen.insert(next) {
                // Entered a smaller loop: report it from where it starts.
                let pos = path.iter().position(|n| *n == next).unwrap();
                return Some(path[pos..].iter().map(|n| g[*n]).collect());
            }
            path.push(next);
            cur = next;
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::parse;
    use std::path::Path;

    #[test]
    fn cycles_are_named() {
        let p = parse(
            Path::new("p.yaml"),
            "stages:\n  a:\n    uses: test_map\n    inputs: {src: c}\n  b:\n    uses: test_map\n    inputs: {src: a}\n  c:\n    uses: test_map\n    inputs: {src: b}\n",
            &[],
        )
        .unwrap();
        let e = Dag::build(&p).err().unwrap();
        assert!(e.message.contains("a -> b -> c -> a"), "{e}");
        let p = parse(
            Path::new("p.yaml"),
            "stages:\n  a:\n    uses: test_map\n    inputs: {src: a}\n",
            &[],
        )
        .unwrap();
        assert!(Dag::build(&p).err().unwrap().message.contains("a -> a"));
    }

    #[test]
    fn order_is_topological_and_stable() {
        let p = parse(
            Path::new("p.yaml"),
            "stages:\n  m:\n    uses: test_map\n    inputs: {src: s, extra: t}\n  s:\n    uses: test_source\n  t:\n    uses: test_source\n",
            &[],
        )
        .unwrap();
        let d = Dag::build(&p).unwrap();
        assert_eq!(d.order, vec![1, 2, 0]);
        assert_eq!(d.ancestors_and_self(0), BTreeSet::from([0, 1, 2]));
        assert_eq!(d.descendants_and_self(1), BTreeSet::from([0, 1]));
    }
}
