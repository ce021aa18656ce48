// pipeline.io._leafbuild: OpenVDB leaves of a FloatGrid made from 8^3 blocks in C++, bulk
// reads of a FloatGrid's values at points and on a strided box (the export's samplers), and
// the .vdb file writer that releases the GIL (write_file).
//
// pyopenvdb's copyFromArray (tools::copyFromDense) is the only bulk write pyopenvdb 10 has. It
// holds the GIL, plans its blocks from a dense box, and prunes the whole tree's tiles at the end
// of every call, and pipeline.io.vdbgrids.write_batched calls it once per run of leaves along z
// (thousands of calls per grid). This module makes the same leaves from the BlockGrid layout
// directly: the leaves are filled in parallel (TBB, without the GIL) and then added to the tree
// serially, and the tiles are pruned once (finish). The result is voxel for voxel what
// copyFromArray makes from the same values: a voxel is active where |v - background| > 0
// (the tolerance copyFromArray is called with; NaN is not), an inactive voxel holds the
// background, a block whose 512 voxels are all active with one value becomes an active tile of
// the leaf's size, a block with no active voxel adds nothing (what was there stays), any other
// block replaces what was there (copyFromDense overwrites a whole leaf's box too).
//
// The grid object comes from pyopenvdb (boost.python, FloatGrid::Ptr holder); this module is
// built against the same OpenVDB and boost.python (Debian's libopenvdb-dev, libboost-python-dev)
// by the package's own build (setup.py), so extract<FloatGrid::Ptr> finds pyopenvdb's registration.

#define BOOST_BIND_GLOBAL_PLACEHOLDERS
#include <Python.h>

#include <boost/python.hpp>
#include <openvdb/io/File.h>
#include <openvdb/openvdb.h>
#include <openvdb/tools/Count.h>
#include <openvdb/tools/Prune.h>
#include <openvdb/tools/SignedFloodFill.h>
#include <openvdb/tree/NodeManager.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <cmath>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

namespace py = boost::python;
using openvdb::Coord;
using openvdb::FloatGrid;
using LeafT = FloatGrid::TreeType::LeafNodeType;

namespace {

constexpr Py_ssize_t VOXELS = LeafT::SIZE;  // 512

// A C-contiguous buffer of a NumPy array, released with the object.
class Buffer {
public:
    Buffer(const py::object& obj, const char* what, const char* formats, Py_ssize_t itemsize) {
        if (PyObject_GetBuffer(obj.ptr(), &view_, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) != 0) {
            py::throw_error_already_set();
        }
        const std::string fmt = view_.format ? view_.format : "B";
        const char code = fmt.empty() ? 'B' : fmt.back();
        if (view_.itemsize != itemsize || std::string(formats).find(code) == std::string::npos) {
            PyBuffer_Release(&view_);
            throw std::invalid_argument(std::string(what) + ": wrong element type '" + fmt + "'");
        }
    }
    ~Buffer() { PyBuffer_Release(&view_); }
    Buffer(const Buffer&) = delete;
    Buffer& operator=(const Buffer&) = delete;
    template <typename T> const T* data() const { return static_cast<const T*>(view_.buf); }
    Py_ssize_t count() const { return view_.len / view_.itemsize; }

private:
    Py_buffer view_{};
};

// What one block becomes: nothing, a leaf, or an active tile of the leaf's size.
struct Made {
    LeafT* leaf = nullptr;
    float tile = 0.0f;
    bool is_tile = false;
};

Made make_block(const float* v, const bool* a, const Coord& origin, float scale, float bg) {
    auto leaf = std::make_unique<LeafT>(origin, bg, false);
    for (Py_ssize_t n = 0; n < VOXELS; ++n) {
        const float x = v[n] * scale;
        if (a[n] && std::abs(x - bg) > 0.0f) leaf->setValueOn(static_cast<openvdb::Index>(n), x);  // NaN: off
    }
    Made out;
    float value;
    bool on;
    if (leaf->isEmpty()) return out;
    if (leaf->isConstant(value, on) && on) {  // every voxel active with one value
        out.is_tile = true;
        out.tile = value;
        return out;
    }
    out.leaf = leaf.release();
    return out;
}

Coord coord_at(const std::int64_t* o, Py_ssize_t row) {
    return Coord(static_cast<int>(o[3 * row]), static_cast<int>(o[3 * row + 1]), static_cast<int>(o[3 * row + 2]));
}

// Whether every coordinate of ``origins`` is a multiple of ``cell``.
void check_aligned(const std::int64_t* o, Py_ssize_t n, int cell, const char* what) {
    for (Py_ssize_t t = 0; t < 3 * n; ++t) {
        if (o[t] % cell != 0) throw std::invalid_argument(std::string(what) + ": origins must be multiples of " + std::to_string(cell));
    }
}

// Add blocks (origins (n, 3) int64; values (n, 8, 8, 8) float32; active (n, 8, 8, 8) bool)
// times ``scale`` to ``grid``. Returns (leaves added, tiles added).
py::tuple add_blocks(py::object grid_obj, py::object origins_obj, py::object values_obj,
                     py::object active_obj, float scale) {
    FloatGrid::Ptr grid = py::extract<FloatGrid::Ptr>(grid_obj);
    Buffer origins(origins_obj, "origins", "lq", 8);
    Buffer values(values_obj, "values", "f", 4);
    Buffer active(active_obj, "active", "?", 1);
    const Py_ssize_t n = origins.count() / 3;
    if (origins.count() != 3 * n || values.count() != n * VOXELS || active.count() != n * VOXELS) {
        throw std::invalid_argument("add_blocks: origins (n, 3), values and active (n, 8, 8, 8) expected");
    }
    const std::int64_t* o = origins.data<std::int64_t>();
    const float* v = values.data<float>();
    const bool* a = active.data<bool>();
    check_aligned(o, n, LeafT::DIM, "add_blocks");
    const float bg = grid->background();
    std::vector<Made> made(static_cast<size_t>(n));
    Py_BEGIN_ALLOW_THREADS
    tbb::parallel_for(tbb::blocked_range<Py_ssize_t>(0, n, 64), [&](const tbb::blocked_range<Py_ssize_t>& r) {
        for (Py_ssize_t b = r.begin(); b < r.end(); ++b) {
            made[b] = make_block(v + b * VOXELS, a + b * VOXELS, coord_at(o, b), scale, bg);
        }
    });
    Py_END_ALLOW_THREADS
    openvdb::tree::ValueAccessor<FloatGrid::TreeType> acc(grid->tree());
    long leaves = 0, tiles = 0;
    for (Py_ssize_t b = 0; b < n; ++b) {
        if (made[b].leaf) {
            acc.addLeaf(made[b].leaf);  // the tree owns it now
            ++leaves;
        } else if (made[b].is_tile) {
            acc.addTile(1, coord_at(o, b), made[b].tile, true);
            ++tiles;
        }
    }
    return py::make_tuple(leaves, tiles);
}

using Vec3Grid = openvdb::Vec3SGrid;
using Vec3Leaf = Vec3Grid::TreeType::LeafNodeType;

// Add blocks of an attribute grid (origins (n, 3) int64; values (n, 8, 8, 8, 3) float32; active
// (n, 8, 8, 8) bool) to a Vec3SGrid: every active voxel is on with its value, whatever it is (an
// attribute covers its voxels even where it equals the background), the others hold the
// background; a block whose voxels are all on with one value becomes an active tile, a block
// with none adds nothing. pipeline.io.vdbgrids.attribute_grid made the same grid with one
// copyFromArray per block under a sentinel background (1.9 s of the colour-bands config at 512^3).
py::tuple add_vec3_blocks(py::object grid_obj, py::object origins_obj, py::object values_obj, py::object active_obj) {
    Vec3Grid::Ptr grid = py::extract<Vec3Grid::Ptr>(grid_obj);
    Buffer origins(origins_obj, "origins", "lq", 8);
    Buffer values(values_obj, "values", "f", 4);
    Buffer active(active_obj, "active", "?", 1);
    const Py_ssize_t n = origins.count() / 3;
    if (origins.count() != 3 * n || values.count() != 3 * n * VOXELS || active.count() != n * VOXELS) {
        throw std::invalid_argument("add_vec3_blocks: origins (n, 3), values (n, 8, 8, 8, 3), active (n, 8, 8, 8) expected");
    }
    const std::int64_t* o = origins.data<std::int64_t>();
    const float* v = values.data<float>();
    const bool* a = active.data<bool>();
    check_aligned(o, n, Vec3Leaf::DIM, "add_vec3_blocks");
    const openvdb::Vec3s bg = grid->background();
    std::vector<Vec3Leaf*> leaves(static_cast<size_t>(n), nullptr);
    std::vector<openvdb::Vec3s> tiles(static_cast<size_t>(n));
    std::vector<char> is_tile(static_cast<size_t>(n), 0);
    Py_BEGIN_ALLOW_THREADS
    tbb::parallel_for(tbb::blocked_range<Py_ssize_t>(0, n, 64), [&](const tbb::blocked_range<Py_ssize_t>& r) {
        for (Py_ssize_t b = r.begin(); b < r.end(); ++b) {
            auto leaf = std::make_unique<Vec3Leaf>(coord_at(o, b), bg, false);
            const float* vb = v + 3 * b * VOXELS;
            const bool* ab = a + b * VOXELS;
            for (Py_ssize_t q = 0; q < VOXELS; ++q) {
                if (ab[q]) leaf->setValueOn(static_cast<openvdb::Index>(q), openvdb::Vec3s(vb[3 * q], vb[3 * q + 1], vb[3 * q + 2]));
            }
            if (leaf->isEmpty()) continue;
            openvdb::Vec3s value;
            bool on;
            if (leaf->isConstant(value, on) && on) {
                is_tile[b] = 1;
                tiles[b] = value;
                continue;
            }
            leaves[b] = leaf.release();
        }
    });
    Py_END_ALLOW_THREADS
    openvdb::tree::ValueAccessor<Vec3Grid::TreeType> acc(grid->tree());
    long n_leaves = 0, n_tiles = 0;
    for (Py_ssize_t b = 0; b < n; ++b) {
        if (leaves[b]) {
            acc.addLeaf(leaves[b]);
            ++n_leaves;
        } else if (is_tile[b]) {
            acc.addTile(1, coord_at(o, b), tiles[b], true);
            ++n_tiles;
        }
    }
    return py::make_tuple(n_leaves, n_tiles);
}

// Active constant tiles of edge ``cell`` (8: a leaf's size, tree level 1; 128: an internal node's
// child, level 2) at ``origins`` (n, 3) int64, multiples of ``cell``, with ``values`` (n,) float32:
// what Tree::fill over each tile's box makes (a tile at that level replacing whatever was
// there), one accessor call per tile instead of one Python call per run of tiles.
long add_tiles(py::object grid_obj, py::object origins_obj, py::object values_obj, int cell) {
    FloatGrid::Ptr grid = py::extract<FloatGrid::Ptr>(grid_obj);
    Buffer origins(origins_obj, "origins", "lq", 8);
    Buffer values(values_obj, "values", "f", 4);
    const Py_ssize_t n = origins.count() / 3;
    if (origins.count() != 3 * n || values.count() != n) {
        throw std::invalid_argument("add_tiles: origins (n, 3) and values (n,) expected");
    }
    openvdb::Index level;
    if (cell == static_cast<int>(LeafT::DIM)) level = 1;
    else if (cell == static_cast<int>(FloatGrid::TreeType::RootNodeType::ChildNodeType::ChildNodeType::DIM)) level = 2;
    else throw std::invalid_argument("add_tiles: cell must be 8 or 128");
    const std::int64_t* o = origins.data<std::int64_t>();
    const float* v = values.data<float>();
    check_aligned(o, n, cell, "add_tiles");
    openvdb::tree::ValueAccessor<FloatGrid::TreeType> acc(grid->tree());
    for (Py_ssize_t t = 0; t < n; ++t) acc.addTile(level, coord_at(o, t), v[t], true);
    return static_cast<long>(n);
}

// A writable C-contiguous float32 buffer (an output array given by the caller).
class OutBuffer {
public:
    OutBuffer(const py::object& obj, const char* what) {
        if (PyObject_GetBuffer(obj.ptr(), &view_, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) != 0) {
            py::throw_error_already_set();
        }
        const std::string fmt = view_.format ? view_.format : "B";
        if (view_.itemsize != 4 || fmt.empty() || fmt.back() != 'f') {
            PyBuffer_Release(&view_);
            throw std::invalid_argument(std::string(what) + ": a writable float32 array expected");
        }
    }
    ~OutBuffer() { PyBuffer_Release(&view_); }
    OutBuffer(const OutBuffer&) = delete;
    OutBuffer& operator=(const OutBuffer&) = delete;
    float* data() const { return static_cast<float*>(view_.buf); }
    Py_ssize_t count() const { return view_.len / 4; }

private:
    Py_buffer view_{};
};

using ConstAccessor = openvdb::tree::ValueAccessor<const FloatGrid::TreeType>;

// Values (active or not: leaf values, tiles, the background, as OpenVDB stores them) at integer
// voxels ``ijk`` (n, 3) int64 into ``out`` (n,) float32, in parallel (an accessor per range).
void sample(py::object grid_obj, py::object ijk_obj, py::object out_obj) {
    FloatGrid::Ptr grid = py::extract<FloatGrid::Ptr>(grid_obj);
    Buffer ijk(ijk_obj, "ijk", "lq", 8);
    OutBuffer out(out_obj, "out");
    const Py_ssize_t n = ijk.count() / 3;
    if (ijk.count() != 3 * n || out.count() != n) throw std::invalid_argument("sample: ijk (n, 3) and out (n,) expected");
    const std::int64_t* p = ijk.data<std::int64_t>();
    float* o = out.data();
    const FloatGrid::TreeType& tree = grid->constTree();
    Py_BEGIN_ALLOW_THREADS
    tbb::parallel_for(tbb::blocked_range<Py_ssize_t>(0, n, 4096), [&](const tbb::blocked_range<Py_ssize_t>& r) {
        ConstAccessor acc(tree);
        for (Py_ssize_t q = r.begin(); q < r.end(); ++q) {
            o[q] = acc.getValue(coord_at(p, q));
        }
    });
    Py_END_ALLOW_THREADS
}

// Values at lo + stride * (mx, my, mz) for m < dims into ``out`` (dims[2], dims[1], dims[0])
// float32, x fastest (VTK's point order), in parallel over z-planes.
void strided_box(py::object grid_obj, py::tuple lo, py::tuple dims, int stride, py::object out_obj) {
    FloatGrid::Ptr grid = py::extract<FloatGrid::Ptr>(grid_obj);
    OutBuffer out(out_obj, "out");
    const int x0 = py::extract<int>(lo[0]), y0 = py::extract<int>(lo[1]), z0 = py::extract<int>(lo[2]);
    const Py_ssize_t nx = py::extract<Py_ssize_t>(dims[0]), ny = py::extract<Py_ssize_t>(dims[1]),
                     nz = py::extract<Py_ssize_t>(dims[2]);
    if (stride < 1 || nx < 0 || ny < 0 || nz < 0 || out.count() != nx * ny * nz) {
        throw std::invalid_argument("strided_box: out must hold dims[0] * dims[1] * dims[2] values, stride >= 1");
    }
    float* o = out.data();
    const FloatGrid::TreeType& tree = grid->constTree();
    Py_BEGIN_ALLOW_THREADS
    tbb::parallel_for(tbb::blocked_range<Py_ssize_t>(0, nz), [&](const tbb::blocked_range<Py_ssize_t>& r) {
        ConstAccessor acc(tree);
        for (Py_ssize_t mz = r.begin(); mz < r.end(); ++mz) {
            for (Py_ssize_t my = 0; my < ny; ++my) {
                float* row = o + (mz * ny + my) * nx;
                for (Py_ssize_t mx = 0; mx < nx; ++mx) {
                    row[mx] = acc.getValue(Coord(x0 + static_cast<int>(stride * mx), y0 + static_cast<int>(stride * my),
                                                 z0 + static_cast<int>(stride * mz)));
                }
            }
        }
    });
    Py_END_ALLOW_THREADS
}

// Every value of a node negated: a leaf's 512 voxels (active or not), an internal node's or the
// root's tiles (their value iterators skip the children).
struct NegateAll {
    void operator()(LeafT& leaf) const {
        float* v = leaf.buffer().data();
        for (openvdb::Index n = 0; n < LeafT::SIZE; ++n) v[n] = -v[n];
    }
    template <typename NodeT> void operator()(NodeT& node) const {
        for (auto it = node.beginValueAll(); it; ++it) it.setValue(-*it);
    }
};

// The FRep signs of a grid whose leaves hold -f (the level-set convention, background +bg):
// OpenVDB's sign flood fill (inactive values and tiles inside -bg, outside +bg), then every
// value negated, the background included (active f, inside +bg, outside -bg: SPEC's frep
// row). pipeline.io.vdbgrids._frep_signed did this with pyopenvdb's signedFloodFill, an AX
// negation of the active values and a background change that swapped +bg and -bg on the
// inactive values: three passes, the GIL held, an AX kernel compiled per grid. Same values.
void frep_signs(py::object grid_obj) {
    FloatGrid::Ptr grid = py::extract<FloatGrid::Ptr>(grid_obj);
    Py_BEGIN_ALLOW_THREADS
    auto& tree = grid->tree();
    openvdb::tools::signedFloodFill(tree);
    openvdb::tree::NodeManager<FloatGrid::TreeType> nodes(tree);
    nodes.foreachTopDown(NegateAll());
    tree.root().setBackground(-tree.background(), /*updateChildNodes=*/false);
    Py_END_ALLOW_THREADS
}

// (min, max) of the active values, voxels and tiles: what Grid::evalMinMax gives ((0, 0) when
// nothing is active), by OpenVDB's threaded reduction (tools::minMax) without the GIL. The
// serial evalMinMax held the GIL for 0.2 s on the demo's hfrep grid at 1024^3.
py::tuple min_max(py::object grid_obj) {
    FloatGrid::Ptr grid = py::extract<FloatGrid::Ptr>(grid_obj);
    if (!grid->constTree().cbeginValueOn()) return py::make_tuple(0.0f, 0.0f);
    openvdb::math::MinMax<float> r;
    Py_BEGIN_ALLOW_THREADS
    r = openvdb::tools::minMax(grid->constTree(), /*threaded=*/true);
    Py_END_ALLOW_THREADS
    return py::make_tuple(r.min(), r.max());
}

// A pyopenvdb grid of one of the types pyopenvdb 10 registers (FloatGrid, Vec3SGrid, BoolGrid).
openvdb::GridBase::Ptr as_grid(const py::object& obj) {
    if (py::extract<FloatGrid::Ptr>(obj).check()) return py::extract<FloatGrid::Ptr>(obj)();
    if (py::extract<openvdb::Vec3SGrid::Ptr>(obj).check()) return py::extract<openvdb::Vec3SGrid::Ptr>(obj)();
    if (py::extract<openvdb::BoolGrid::Ptr>(obj).check()) return py::extract<openvdb::BoolGrid::Ptr>(obj)();
    throw std::invalid_argument("write_file: not a FloatGrid, Vec3SGrid or BoolGrid");
}

// What pyopenvdb.write(path, grids, metadata) does (io::File::write of the grids with the file
// metadata, which pyopenvdb's own dict -> MetaMap converter makes), without the GIL, so a
// Python thread can write while the interpreter goes on. ``halves[i]``: store grid i's floats
// as halves. The grids written are shallow copies (the same trees) that carry the flags: the
// caller's grids are only read, as other threads may be reading them at the same time.
void write_file(py::list grids, const std::string& path, py::object metadata, py::list halves) {
    const Py_ssize_t n = py::len(grids);
    if (py::len(halves) != n) throw std::invalid_argument("write_file: one half-float flag per grid expected");
    openvdb::GridPtrVec out;
    for (Py_ssize_t i = 0; i < n; ++i) {
        openvdb::GridBase::Ptr copy = as_grid(grids[i])->copyGrid();
        copy->setSaveFloatAsHalf(py::extract<bool>(halves[i]));
        out.push_back(copy);
    }
    const openvdb::MetaMap meta = py::extract<openvdb::MetaMap>(metadata);
    std::string error;
    Py_BEGIN_ALLOW_THREADS
    try {
        openvdb::io::File file(path);
        file.write(out, meta);
        file.close();
    } catch (const std::exception& e) {
        error = e.what();
    }
    Py_END_ALLOW_THREADS
    if (!error.empty()) throw std::runtime_error(error);
}

// Prune the tiles as copyFromArray does after every call (tools::pruneTiles, tolerance 0).
void finish(py::object grid_obj) {
    FloatGrid::Ptr grid = py::extract<FloatGrid::Ptr>(grid_obj);
    Py_BEGIN_ALLOW_THREADS
    openvdb::tools::pruneTiles(grid->tree(), 0.0f);
    Py_END_ALLOW_THREADS
}

void translate(const std::invalid_argument& e) { PyErr_SetString(PyExc_ValueError, e.what()); }

}  // namespace

BOOST_PYTHON_MODULE(_leafbuild) {
    py::register_exception_translator<std::invalid_argument>(&translate);
    py::def("add_blocks", &add_blocks, (py::arg("grid"), py::arg("origins"), py::arg("values"), py::arg("active"),
                                        py::arg("scale") = 1.0f));
    py::def("add_vec3_blocks", &add_vec3_blocks, (py::arg("grid"), py::arg("origins"), py::arg("values"),
                                                  py::arg("active")));
    py::def("add_tiles", &add_tiles, (py::arg("grid"), py::arg("origins"), py::arg("values"), py::arg("cell")));
    py::def("finish", &finish, py::arg("grid"));
    py::def("frep_signs", &frep_signs, py::arg("grid"));
    py::def("min_max", &min_max, py::arg("grid"));
    py::def("sample", &sample, (py::arg("grid"), py::arg("ijk"), py::arg("out")));
    py::def("write_file", &write_file, (py::arg("grids"), py::arg("path"), py::arg("metadata"), py::arg("halves")));
    py::def("strided_box", &strided_box, (py::arg("grid"), py::arg("lo"), py::arg("dims"), py::arg("stride"),
                                          py::arg("out")));
}
