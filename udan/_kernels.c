/* udan._kernels: the integer bookkeeping of the grid world and of grouping, and the observation
 * encoder, as loops in C.
 *
 * Why: numpy pays a fixed price per call (~1-2 us, more inside a loop that alternates with
 * onnxruntime), and these steps are each a few dozen numpy passes over a few agents (the
 * edge's 5 cars) or data-dependent searches (neighbours ring by ring, bridge rounds, conflict
 * fixed points) that numpy can only express as many passes. One C loop does each in one pass.
 *
 * Each function is the one implementation its Python caller documents (udan/envs/grouping.py,
 * rules.py, observe.py and arena.py; the edge's safety filter and fleet cells in edge/safety.py
 * and edge/decide.py): those callers check and convert the arguments, allocate the outputs and
 * own the documentation; this file checks only what it must not get wrong (buffer types,
 * shapes and indices), so that no argument can make it read or write out of bounds. Arrays
 * arrive through the buffer protocol, C-contiguous. Scratch memory is kept between calls (the
 * interpreter lock is held throughout), so a step allocates nothing.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* ---------------------------------------------------------------- buffers and scratch */

typedef struct {
    Py_buffer view;
    int held;
} Array;

/* The buffer of `obj` as `ndim`-dimensional C-contiguous items of `size` bytes whose
 * struct format character is one of `kinds`; writable if asked. */
static int take(PyObject *obj, Array *a, const char *name, const char *kinds, Py_ssize_t size,
                int ndim, int writable) {
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, &a->view, flags) < 0) return -1;
    a->held = 1;
    const char *format = a->view.format ? a->view.format : "B";
    if (*format == '@' || *format == '=' || *format == '<') format++;
    if (a->view.itemsize != size || strlen(format) != 1 || !strchr(kinds, *format)) {
        PyErr_Format(PyExc_TypeError, "%s: wrong item type '%s'", name, a->view.format);
        return -1;
    }
    if (a->view.ndim != ndim) {
        PyErr_Format(PyExc_ValueError, "%s: %d dimensions, not %d", name, a->view.ndim, ndim);
        return -1;
    }
    return 0;
}

static void release(Array *arrays, int count) {
    for (int i = 0; i < count; i++)
        if (arrays[i].held) PyBuffer_Release(&arrays[i].view);
}

#define I64 "lq", 8
#define BOOL "?", 1
#define U8 "B", 1
#define F32 "f", 4
#define SHAPE(a, i) ((a).view.shape[i])

static int same_shape(const Array *a, const Array *b, int dims, const char *what) {
    for (int i = 0; i < dims; i++)
        if (SHAPE(*a, i) != SHAPE(*b, i)) {
            PyErr_Format(PyExc_ValueError, "%s: shapes do not match", what);
            return 0;
        }
    return 1;
}

static char *scratch_memory = NULL;
static size_t scratch_bytes = 0;

/* At least `bytes` of scratch memory, kept for the next call (the lock is held). */
static void *scratch(size_t bytes) {
    if (bytes > scratch_bytes || !scratch_memory) {
        bytes = bytes > 64 ? bytes : 64;
        char *grown = realloc(scratch_memory, bytes);
        if (!grown) {
            PyErr_NoMemory();
            return NULL;
        }
        scratch_memory = grown;
        scratch_bytes = bytes;
    }
    return scratch_memory;
}

/* ---------------------------------------------------------------- nearest agents */

static void sort_slots(int32_t *slots, Py_ssize_t count) {
    for (Py_ssize_t i = 1; i < count; i++) {
        int32_t slot = slots[i];
        Py_ssize_t j = i;
        for (; j > 0 && slots[j - 1] > slot; j--) slots[j] = slots[j - 1];
        slots[j] = slot;
    }
}

/* Appends the agents of grid cell `cell` to ring[found...]; returns the new count. Without
 * shared cells it does not branch on whether the cell holds anyone (most do not). */
static inline Py_ssize_t gather(const int32_t *head, const int32_t *next, Py_ssize_t cell,
                                int shared, int32_t *ring, Py_ssize_t found) {
    int32_t j = head[cell];
    if (!shared) {
        ring[found] = j;
        return found + (j >= 0);
    }
    for (; j >= 0; j = next[j]) ring[found++] = j;
    return found;
}

/* One arena: each present agent's `count` nearest present agents, itself first, by grid
 * distance then slot; -1 where there are fewer, and in the rows of absent agents. Agents are
 * looked up ring by ring around each agent on a grid over the agents' bounding box, each
 * cell holding its agents in slot order (several may share a cell). */
static int nearest_one(const int64_t *pos, const char *present, Py_ssize_t n, Py_ssize_t count,
                       int64_t *out) {
    for (Py_ssize_t i = 0; i < n * count; i++) out[i] = -1;
    int64_t row_lo = INT64_MAX, row_hi = INT64_MIN, col_lo = INT64_MAX, col_hi = INT64_MIN;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (!present[i]) continue;
        int64_t r = pos[2 * i], c = pos[2 * i + 1];
        row_lo = r < row_lo ? r : row_lo;
        row_hi = r > row_hi ? r : row_hi;
        col_lo = c < col_lo ? c : col_lo;
        col_hi = c > col_hi ? c : col_hi;
    }
    if (row_lo > row_hi || count == 0) return 0;
    if (row_hi - row_lo >= (1 << 22) || col_hi - col_lo >= (1 << 22) ||
        (row_hi - row_lo + 1) * (col_hi - col_lo + 1) > (1 << 22)) {
        PyErr_SetString(PyExc_ValueError, "nearest: the agents span more than 2^22 cells");
        return -1;
    }
    Py_ssize_t rows = (Py_ssize_t)(row_hi - row_lo + 1), cols = (Py_ssize_t)(col_hi - col_lo + 1);
    int32_t *head = scratch(sizeof(int32_t) * (size_t)(rows * cols + 2 * n));
    if (!head) return -1;
    int32_t *next = head + rows * cols, *ring = next + n;
    int shared = 0;  /* some cell holds several agents: follow the lists (else one look each) */
    for (Py_ssize_t i = 0; i < rows * cols; i++) head[i] = -1;
    for (Py_ssize_t i = n - 1; i >= 0; i--) {  /* pushed last slot first: lists ascend */
        if (!present[i]) continue;
        Py_ssize_t cell = (Py_ssize_t)(pos[2 * i] - row_lo) * cols + (pos[2 * i + 1] - col_lo);
        shared |= head[cell] >= 0;
        next[i] = head[cell];
        head[cell] = (int32_t)i;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        if (!present[i]) continue;
        int64_t *row = out + i * count;
        Py_ssize_t filled = 0;
        row[filled++] = i;
        Py_ssize_t r = (Py_ssize_t)(pos[2 * i] - row_lo), c = (Py_ssize_t)(pos[2 * i + 1] - col_lo);
        for (int32_t j = head[r * cols + c]; j >= 0 && filled < count; j = next[j])
            if (j != i) row[filled++] = j;
        Py_ssize_t reach = (r > rows - 1 - r ? r : rows - 1 - r) + (c > cols - 1 - c ? c : cols - 1 - c);
        for (Py_ssize_t d = 1; d <= reach && filled < count; d++) {
            Py_ssize_t found = 0;
            Py_ssize_t dr_lo = -d > -r ? -d : -r, dr_hi = d < rows - 1 - r ? d : rows - 1 - r;
            for (Py_ssize_t dr = dr_lo; dr <= dr_hi; dr++) {
                Py_ssize_t along = d - (dr < 0 ? -dr : dr), base = (r + dr) * cols;
                if (c - along >= 0) found = gather(head, next, base + c - along, shared, ring, found);
                if (along && c + along < cols)
                    found = gather(head, next, base + c + along, shared, ring, found);
            }
            sort_slots(ring, found);
            for (Py_ssize_t k = 0; k < found && filled < count; k++) row[filled++] = ring[k];
        }
    }
    return 0;
}

static PyObject *nearest(PyObject *self, PyObject *args) {
    PyObject *pos_o, *present_o, *out_o;
    if (!PyArg_ParseTuple(args, "OOO:nearest", &pos_o, &present_o, &out_o)) return NULL;
    Array a[3];
    memset(a, 0, sizeof a);
    PyObject *result = NULL;
    if (take(pos_o, &a[0], "pos", I64, 3, 0) || take(present_o, &a[1], "present", BOOL, 2, 0) ||
        take(out_o, &a[2], "out", I64, 3, 1))
        goto done;
    Py_ssize_t m = SHAPE(a[1], 0), n = SHAPE(a[1], 1), count = SHAPE(a[2], 2);
    if (!same_shape(&a[0], &a[1], 2, "nearest pos/present") ||
        !same_shape(&a[2], &a[1], 2, "nearest out/present"))
        goto done;
    if (SHAPE(a[0], 2) != 2) {
        PyErr_SetString(PyExc_ValueError, "nearest: positions are (row, col) pairs");
        goto done;
    }
    const int64_t *pos = a[0].view.buf;
    const char *present = a[1].view.buf;
    int64_t *out = a[2].view.buf;
    for (Py_ssize_t k = 0; k < m; k++)
        if (nearest_one(pos + 2 * n * k, present + n * k, n, count, out + n * count * k) < 0)
            goto done;
    result = Py_NewRef(Py_None);
done:
    release(a, 3);
    return result;
}

/* ---------------------------------------------------------------- leaders */

typedef struct {
    double prob;
    int64_t slot;
} Ranked;

/* Sorts ranked[0..count) by prob, highest first, equal ones in the order given: a stable
 * bottom-up merge sort between `ranked` and `tmp`; returns the one that holds the result. */
static Ranked *sort_ranked(Ranked *ranked, Ranked *tmp, Py_ssize_t count) {
    for (Py_ssize_t width = 1; width < count; width *= 2) {
        for (Py_ssize_t lo = 0; lo < count; lo += 2 * width) {
            Py_ssize_t mid = lo + width < count ? lo + width : count;
            Py_ssize_t hi = lo + 2 * width < count ? lo + 2 * width : count;
            Py_ssize_t i = lo, j = mid, k = lo;
            while (i < mid && j < hi)
                tmp[k++] = ranked[j].prob > ranked[i].prob ? ranked[j++] : ranked[i++];
            while (i < mid) tmp[k++] = ranked[i++];
            while (j < hi) tmp[k++] = ranked[j++];
        }
        Ranked *merged = tmp;
        tmp = ranked;
        ranked = merged;
    }
    return ranked;
}

static PyObject *leaders(PyObject *self, PyObject *args) {
    PyObject *prob_o, *present_o, *out_o;
    double threshold;
    if (!PyArg_ParseTuple(args, "OOdO:leaders", &prob_o, &present_o, &threshold, &out_o))
        return NULL;
    Array a[3];
    memset(a, 0, sizeof a);
    PyObject *result = NULL;
    if (take(prob_o, &a[0], "prob", "d", 8, 1, 0) || take(present_o, &a[1], "present", BOOL, 1, 0) ||
        take(out_o, &a[2], "out", I64, 1, 1))
        goto done;
    Py_ssize_t n = SHAPE(a[1], 0), count = 0;
    if (SHAPE(a[0], 0) != n || SHAPE(a[2], 0) != n) {
        PyErr_SetString(PyExc_ValueError, "leaders: one probability and place per slot");
        goto done;
    }
    const double *prob = a[0].view.buf;
    const char *present = a[1].view.buf;
    int64_t *out = a[2].view.buf;
    Ranked *ranked = scratch(sizeof(Ranked) * (size_t)(2 * n));
    if (!ranked) goto done;
    for (Py_ssize_t i = 0; i < n; i++)
        if (present[i] && prob[i] > threshold) ranked[count++] = (Ranked){prob[i], i};
    Ranked *sorted = sort_ranked(ranked, ranked + n, count);
    for (Py_ssize_t i = 0; i < count; i++) out[i] = sorted[i].slot;
    result = PyLong_FromSsize_t(count);
done:
    release(a, 3);
    return result;
}

/* ---------------------------------------------------------------- bridge rounds */

static PyObject *round_order(PyObject *self, PyObject *args) {
    PyObject *groups_o, *order_o, *sizes_o;
    if (!PyArg_ParseTuple(args, "OOO:round_order", &groups_o, &order_o, &sizes_o)) return NULL;
    Array a[3];
    memset(a, 0, sizeof a);
    PyObject *result = NULL;
    if (take(groups_o, &a[0], "groups", I64, 2, 0) || take(order_o, &a[1], "order", I64, 1, 1) ||
        take(sizes_o, &a[2], "sizes", I64, 1, 1))
        goto done;
    Py_ssize_t n_groups = SHAPE(a[0], 0), width = SHAPE(a[0], 1);
    if (SHAPE(a[1], 0) != n_groups || SHAPE(a[2], 0) != n_groups) {
        PyErr_SetString(PyExc_ValueError, "round_order: order and sizes need one entry a group");
        goto done;
    }
    const int64_t *groups = a[0].view.buf;
    int64_t *order = a[1].view.buf, *sizes = a[2].view.buf;
    int64_t top = -1;
    for (Py_ssize_t i = 0; i < n_groups * width; i++) {
        if (groups[i] < 0 || groups[i] >= (1 << 24)) {
            PyErr_SetString(PyExc_ValueError, "round_order: members are slots 0 to 2^24 - 1");
            goto done;
        }
        top = groups[i] > top ? groups[i] : top;
    }
    int64_t *last = scratch(sizeof(int64_t) * (size_t)(top + 1 + 2 * n_groups));
    if (!last) goto done;
    int64_t *round_of = last + top + 1, *start = round_of + n_groups, rounds = 0;
    for (int64_t i = 0; i <= top; i++) last[i] = -1;
    for (Py_ssize_t g = 0; g < n_groups; g++) {  /* one round after its members' last */
        const int64_t *members = groups + g * width;
        int64_t r = -1;
        for (Py_ssize_t k = 0; k < width; k++) r = last[members[k]] > r ? last[members[k]] : r;
        round_of[g] = ++r;
        for (Py_ssize_t k = 0; k < width; k++) last[members[k]] = r;
        rounds = r + 1 > rounds ? r + 1 : rounds;
        sizes[g] = 0;
    }
    for (Py_ssize_t g = 0; g < n_groups; g++) sizes[round_of[g]]++;
    for (int64_t r = 0, first = 0; r < rounds; r++) {  /* where each round's groups go */
        start[r] = first;
        first += sizes[r];
    }
    for (Py_ssize_t g = 0; g < n_groups; g++) order[start[round_of[g]]++] = g;
    result = PyLong_FromLongLong(rounds);
done:
    release(a, 3);
    return result;
}

/* ---------------------------------------------------------------- grid rules */

static const int64_t DELTAS[5][2] = {{-1, 0}, {1, 0}, {0, -1}, {0, 1}, {0, 0}};
#define N_ACTIONS 5
#define WAIT 4

/* Bytes of workspace resolve_one needs for n agents on a height x width arena. */
static size_t resolve_work(Py_ssize_t n, Py_ssize_t height, Py_ssize_t width) {
    return sizeof(int32_t) * (size_t)(2 * (height + 2) * (width + 2)) + sizeof(int64_t) * (size_t)(3 * n);
}

/* One arena's simultaneous moves under the conflict rules (udan/envs/rules.py): cells are
 * numbered on the arena bordered by one impassable cell, so a move is one addition. `work`
 * holds resolve_work(n, height, width) bytes, 8-byte aligned. */
static int resolve_one(const int64_t *pos, const int64_t *actions, const char *passable,
                       const char *present, Py_ssize_t n, Py_ssize_t height, Py_ssize_t width,
                       int64_t *out, void *work) {
    Py_ssize_t stride = width + 2, cells = (height + 2) * stride;
    int32_t *occupant = work, *claims = occupant + cells;
    int64_t *cur = (int64_t *)(claims + cells), *dst = cur + n, *done = dst + n;
    for (Py_ssize_t i = 0; i < cells; i++) occupant[i] = -1, claims[i] = 0;
    Py_ssize_t moving = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        done[i] = WAIT;
        if (!present[i]) continue;
        int64_t row = pos[2 * i], col = pos[2 * i + 1], action = actions[i];
        if (row < 0 || row >= height || col < 0 || col >= width) {
            PyErr_Format(PyExc_ValueError, "resolve_moves: agent %zd at (%lld, %lld) is off the "
                         "%zdx%zd arena", i, (long long)row, (long long)col, height, width);
            return -1;
        }
        if (action < 0) action += N_ACTIONS;  /* as numpy indexes ACTION_DELTAS */
        if (action < 0 || action >= N_ACTIONS) {
            PyErr_Format(PyExc_IndexError, "resolve_moves: action %lld of agent %zd is not "
                         "one of the 5", (long long)actions[i], i);
            return -1;
        }
        int64_t to_row = row + DELTAS[action][0], to_col = col + DELTAS[action][1];
        cur[i] = (row + 1) * stride + col + 1;
        int open = to_row >= 0 && to_row < height && to_col >= 0 && to_col < width &&
                   passable[to_row * width + to_col];
        dst[i] = open ? (to_row + 1) * stride + to_col + 1 : cur[i];
        done[i] = action;
        occupant[cur[i]] = (int32_t)i;
        moving += dst[i] != cur[i];
    }
    while (moving) {  /* block every move in conflict at once, until none is */
        for (Py_ssize_t i = 0; i < n; i++)
            if (present[i]) claims[dst[i]]++;
        Py_ssize_t blocked = 0;
        for (Py_ssize_t i = 0; i < n; i++) {
            if (!present[i] || dst[i] == cur[i]) continue;
            int32_t other = occupant[dst[i]];
            if (claims[dst[i]] > 1 || (other >= 0 && dst[other] == cur[i])) {
                done[i] = -1 - WAIT;  /* blocked: marked until this pass has looked at all */
                blocked++;
            }
        }
        for (Py_ssize_t i = 0; i < n; i++) {
            if (present[i]) claims[dst[i]] = 0;
            if (done[i] < 0) dst[i] = cur[i], done[i] = WAIT;
        }
        if (!blocked) break;
        moving -= blocked;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        int64_t action = present[i] && dst[i] != cur[i] ? done[i] : WAIT;
        out[2 * i] = pos[2 * i] + DELTAS[action][0];
        out[2 * i + 1] = pos[2 * i + 1] + DELTAS[action][1];
    }
    return 0;
}

static PyObject *resolve_moves(PyObject *self, PyObject *args) {
    PyObject *pos_o, *actions_o, *passable_o, *present_o, *out_o;
    if (!PyArg_ParseTuple(args, "OOOOO:resolve_moves", &pos_o, &actions_o, &passable_o,
                          &present_o, &out_o))
        return NULL;
    Array a[5];
    memset(a, 0, sizeof a);
    PyObject *result = NULL;
    if (take(pos_o, &a[0], "pos", I64, 3, 0) || take(actions_o, &a[1], "actions", I64, 2, 0) ||
        take(passable_o, &a[2], "passable", BOOL, 3, 0) ||
        take(present_o, &a[3], "present", BOOL, 2, 0) || take(out_o, &a[4], "out", I64, 3, 1))
        goto done;
    Py_ssize_t batch = SHAPE(a[3], 0), n = SHAPE(a[3], 1);
    Py_ssize_t height = SHAPE(a[2], 1), width = SHAPE(a[2], 2);
    if (!same_shape(&a[0], &a[3], 2, "resolve_moves pos/present") ||
        !same_shape(&a[1], &a[3], 2, "resolve_moves actions/present") ||
        !same_shape(&a[4], &a[0], 3, "resolve_moves out/pos") ||
        !same_shape(&a[2], &a[3], 1, "resolve_moves passable/present"))
        goto done;
    if (SHAPE(a[0], 2) != 2) {
        PyErr_SetString(PyExc_ValueError, "resolve_moves: positions are (row, col) pairs");
        goto done;
    }
    const int64_t *pos = a[0].view.buf, *actions = a[1].view.buf;
    const char *passable = a[2].view.buf, *present = a[3].view.buf;
    int64_t *out = a[4].view.buf;
    void *work = scratch(resolve_work(n, height, width));
    if (!work) goto done;
    for (Py_ssize_t b = 0; b < batch; b++)
        if (resolve_one(pos + 2 * n * b, actions + n * b, passable + height * width * b,
                        present + n * b, n, height, width, out + 2 * n * b, work) < 0)
            goto done;
    result = Py_NewRef(Py_None);
done:
    release(a, 5);
    return result;
}

static PyObject *filter_moves(PyObject *self, PyObject *args) {
    PyObject *layout_o, *pos_o, *actions_o, *expected_o, *others_o;
    PyObject *commands_o, *blocked_o, *stopped_o, *dest_o;
    long long free_code, stop;
    if (!PyArg_ParseTuple(args, "OOOOOLLOOOO:filter_moves", &layout_o, &pos_o, &actions_o,
                          &expected_o, &others_o, &free_code, &stop, &commands_o, &blocked_o,
                          &stopped_o, &dest_o))
        return NULL;
    Array a[9];
    memset(a, 0, sizeof a);
    PyObject *result = NULL;
    if (take(layout_o, &a[0], "layout", U8, 2, 0) || take(pos_o, &a[1], "pos", I64, 2, 0) ||
        take(actions_o, &a[2], "actions", I64, 1, 0) ||
        take(expected_o, &a[3], "expected", I64, 2, 0) ||
        take(others_o, &a[4], "others", I64, 2, 0) ||
        take(commands_o, &a[5], "commands", I64, 1, 1) ||
        take(blocked_o, &a[6], "blocked", BOOL, 1, 1) ||
        take(stopped_o, &a[7], "stopped", BOOL, 1, 1) || take(dest_o, &a[8], "dest", I64, 2, 1))
        goto done;
    Py_ssize_t height = SHAPE(a[0], 0), width = SHAPE(a[0], 1), n = SHAPE(a[1], 0);
    if (SHAPE(a[1], 1) != 2 || SHAPE(a[3], 1) != 2 || SHAPE(a[4], 1) != 2 ||
        SHAPE(a[8], 1) != 2 || SHAPE(a[2], 0) != n || SHAPE(a[3], 0) != n ||
        SHAPE(a[5], 0) != n || SHAPE(a[6], 0) != n || SHAPE(a[7], 0) != n ||
        SHAPE(a[8], 0) != n) {
        PyErr_SetString(PyExc_ValueError, "filter_moves: one row per car, cells as pairs");
        goto done;
    }
    const uint8_t *layout = a[0].view.buf;
    const int64_t *pos = a[1].view.buf, *actions = a[2].view.buf, *expected = a[3].view.buf;
    const int64_t *others = a[4].view.buf;
    int64_t *commands = a[5].view.buf, *dest = a[8].view.buf;
    char *blocked = a[6].view.buf, *stopped = a[7].view.buf;
    size_t cells = (size_t)(height * width), ahead = (cells + n + 7) / 8 * 8;
    char *passable = scratch(ahead + sizeof(int64_t) * (size_t)n + resolve_work(n, height, width));
    if (!passable) goto done;
    char *everyone = passable + cells;
    int64_t *moving = (int64_t *)(passable + ahead);
    Py_ssize_t wants = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        const int64_t *want = expected + 2 * i, *cell = pos + 2 * i;
        stopped[i] = want[0] >= 0 && (want[0] != cell[0] || want[1] != cell[1]);
        moving[i] = stopped[i] ? WAIT : actions[i];
        blocked[i] = 0;
        everyone[i] = 1;
        wants += moving[i] != WAIT;
    }
    if (wants) {  /* else nothing moves: nothing can conflict */
        for (size_t c = 0; c < cells; c++) passable[c] = layout[c] == free_code;
        for (Py_ssize_t k = 0; k < SHAPE(a[4], 0); k++) {
            int64_t r = others[2 * k], c = others[2 * k + 1];
            if (r >= 0 && r < height && c >= 0 && c < width) passable[r * width + c] = 0;
        }
        if (resolve_one(pos, moving, passable, everyone, n, height, width, dest,
                        (char *)(moving + n)) < 0)
            goto done;
    } else {
        memcpy(dest, pos, sizeof(int64_t) * (size_t)(2 * n));
    }
    for (Py_ssize_t i = 0; i < n; i++) {  /* a wanted move that did not happen was blocked */
        blocked[i] = moving[i] != WAIT && dest[2 * i] == pos[2 * i] &&
                     dest[2 * i + 1] == pos[2 * i + 1];
        commands[i] = stopped[i] ? stop : blocked[i] ? WAIT : moving[i];
    }
    result = Py_NewRef(Py_None);
done:
    release(a, 9);
    return result;
}

/* ---------------------------------------------------------------- task rewards */

static PyObject *task_rewards(PyObject *self, PyObject *args) {
    PyObject *layout_o, *pos_o, *present_o, *target_o, *t_o, *out_o;
    int find_water;
    long long water;
    if (!PyArg_ParseTuple(args, "pOOOOOLO:task_rewards", &find_water, &layout_o, &pos_o,
                          &present_o, &target_o, &t_o, &water, &out_o))
        return NULL;
    Array a[6];
    memset(a, 0, sizeof a);
    PyObject *result = NULL;
    if (take(layout_o, &a[0], "layout", U8, 3, 0) || take(pos_o, &a[1], "pos", I64, 3, 0) ||
        take(present_o, &a[2], "present", BOOL, 2, 0) ||
        take(target_o, &a[3], "target", I64, 2, 0) || take(t_o, &a[4], "t", I64, 1, 0) ||
        take(out_o, &a[5], "out", F32, 2, 1))
        goto done;
    Py_ssize_t batch = SHAPE(a[2], 0), n = SHAPE(a[2], 1), width = SHAPE(a[0], 2);
    if (!same_shape(&a[1], &a[2], 2, "task_rewards pos/present") ||
        !same_shape(&a[5], &a[2], 2, "task_rewards out/present") ||
        !same_shape(&a[0], &a[2], 1, "task_rewards layout/present") ||
        !same_shape(&a[4], &a[2], 1, "task_rewards t/present") || SHAPE(a[1], 2) != 2 ||
        (!find_water && (SHAPE(a[3], 0) != batch || SHAPE(a[3], 1) != 2))) {
        PyErr_SetString(PyExc_ValueError, "task_rewards: shapes do not match");
        goto done;
    }
    const uint8_t *layout = a[0].view.buf;
    const int64_t *pos = a[1].view.buf, *target = a[3].view.buf, *t = a[4].view.buf;
    const char *present = a[2].view.buf;
    float *out = a[5].view.buf;
    Py_ssize_t plane = SHAPE(a[0], 1) * width;
    for (Py_ssize_t i = 0; i < batch * n; i++) {
        Py_ssize_t b = i / n;
        int64_t row = pos[2 * i], col = pos[2 * i + 1];
        float reward = 0.0f;
        if (present[i] && find_water) {  /* in front of a source: row 1, water in row 0 */
            if (col < 0 || col >= width) {
                PyErr_Format(PyExc_IndexError, "task_rewards: agent %zd at column %lld is off "
                             "the arena", i % n, (long long)col);
                goto done;
            }
            reward = row == 1 && layout[b * plane + col] == water;
        } else if (present[i]) {  /* next to the target, else -1 every fourth step */
            int64_t d_row = row - target[2 * b], d_col = col - target[2 * b + 1];
            int adjacent = (d_row < 0 ? -d_row : d_row) + (d_col < 0 ? -d_col : d_col) == 1;
            reward = adjacent ? 1.0f : t[b] % 4 == 0 ? -1.0f : 0.0f;
        }
        out[i] = reward;
    }
    result = Py_NewRef(Py_None);
done:
    release(a, 6);
    return result;
}

/* ---------------------------------------------------------------- observations */

static PyObject *scene_codes(PyObject *self, PyObject *args) {
    PyObject *layout_o, *pos_o, *present_o, *target_o, *out_o;
    Py_ssize_t view;
    long long agent_bit, target_bit;
    if (!PyArg_ParseTuple(args, "OOOOnLLO:scene_codes", &layout_o, &pos_o, &present_o,
                          &target_o, &view, &agent_bit, &target_bit, &out_o))
        return NULL;
    Array a[5];
    memset(a, 0, sizeof a);
    PyObject *result = NULL;
    if (take(layout_o, &a[0], "padded_layout", U8, 3, 0) || take(pos_o, &a[1], "pos", I64, 3, 0) ||
        take(present_o, &a[2], "present", BOOL, 2, 0) ||
        take(target_o, &a[3], "target", I64, 2, 0) || take(out_o, &a[4], "out", U8, 3, 1))
        goto done;
    Py_ssize_t batch = SHAPE(a[2], 0), n = SHAPE(a[2], 1), hp = SHAPE(a[0], 1), wp = SHAPE(a[0], 2);
    Py_ssize_t targets = SHAPE(a[3], 0);
    if (!same_shape(&a[1], &a[2], 2, "scene_codes pos/present") ||
        !same_shape(&a[4], &a[0], 3, "scene_codes out/padded_layout") ||
        !same_shape(&a[0], &a[2], 1, "scene_codes padded_layout/present") ||
        SHAPE(a[1], 2) != 2 || SHAPE(a[3], 1) != 2 || (targets && targets != batch) ||
        view < 0 || 2 * view >= hp || 2 * view >= wp) {
        PyErr_SetString(PyExc_ValueError, "scene_codes: shapes do not match");
        goto done;
    }
    const int64_t *pos = a[1].view.buf, *target = a[3].view.buf;
    const char *present = a[2].view.buf;
    uint8_t *out = a[4].view.buf;
    Py_ssize_t plane = hp * wp;
    memcpy(out, a[0].view.buf, (size_t)(batch * plane));
    for (Py_ssize_t i = 0; i < batch * n; i++) {
        if (!present[i]) continue;
        int64_t r = pos[2 * i], c = pos[2 * i + 1];
        if (r < 0 || c < 0 || r >= hp - 2 * view || c >= wp - 2 * view) {
            PyErr_Format(PyExc_IndexError, "scene_codes: agent %zd at (%lld, %lld) is off the "
                         "arena", i % n, (long long)r, (long long)c);
            goto done;
        }
        out[(i / n) * plane + (r + view) * wp + c + view] |= (uint8_t)agent_bit;
    }
    for (Py_ssize_t b = 0; b < targets; b++) {  /* (-1, -1), no target seen, is a border cell */
        int64_t r = target[2 * b] + view, c = target[2 * b + 1] + view;
        if (r < 0 || c < 0 || r >= hp || c >= wp) {
            PyErr_SetString(PyExc_IndexError, "scene_codes: a target past the padded codes");
            goto done;
        }
        out[b * plane + r * wp + c] |= (uint8_t)target_bit;
    }
    result = Py_NewRef(Py_None);
done:
    release(a, 5);
    return result;
}

static PyObject *observe(PyObject *self, PyObject *args) {
    PyObject *codes_o, *pos_o, *action_o, *reward_o, *present_o, *bits_o, *out_o;
    Py_ssize_t view, own_bit, row_scale, col_scale;
    if (!PyArg_ParseTuple(args, "OOOOOOnnnnO:observe", &codes_o, &pos_o, &action_o, &reward_o,
                          &present_o, &bits_o, &view, &own_bit, &row_scale, &col_scale, &out_o))
        return NULL;
    Array a[7];
    memset(a, 0, sizeof a);
    PyObject *result = NULL;
    if (take(codes_o, &a[0], "padded_codes", U8, 3, 0) || take(pos_o, &a[1], "pos", I64, 3, 0) ||
        take(action_o, &a[2], "last_action", I64, 2, 0) ||
        take(reward_o, &a[3], "last_reward", F32, 2, 0) ||
        take(present_o, &a[4], "present", BOOL, 2, 0) || take(bits_o, &a[5], "bits", U8, 1, 0) ||
        take(out_o, &a[6], "out", F32, 3, 1))
        goto done;
    Py_ssize_t batch = SHAPE(a[4], 0), n = SHAPE(a[4], 1), channels = SHAPE(a[5], 0);
    Py_ssize_t win = 2 * view + 1, area = win * win, size = SHAPE(a[6], 2);
    Py_ssize_t plane = SHAPE(a[0], 1) * SHAPE(a[0], 2), wp = SHAPE(a[0], 2);
    Py_ssize_t actions = size - channels * area - 3;
    if (!same_shape(&a[1], &a[4], 2, "observe pos/present") ||
        !same_shape(&a[2], &a[4], 2, "observe last_action/present") ||
        !same_shape(&a[3], &a[4], 2, "observe last_reward/present") ||
        !same_shape(&a[6], &a[4], 2, "observe out/present") ||
        !same_shape(&a[0], &a[4], 1, "observe padded_codes/present"))
        goto done;
    if (view < 0 || actions < 0 || SHAPE(a[1], 2) != 2 || row_scale <= 0 || col_scale <= 0) {
        PyErr_SetString(PyExc_ValueError, "observe: inconsistent view, positions or width");
        goto done;
    }
    const uint8_t *codes = a[0].view.buf, *bits = a[5].view.buf;
    const int64_t *pos = a[1].view.buf, *last_action = a[2].view.buf;
    const float *last_reward = a[3].view.buf;
    const char *present = a[4].view.buf;
    float *out = a[6].view.buf;
    Py_ssize_t center = area / 2;
    uint8_t *window = scratch((size_t)area);
    if (!window) goto done;
    for (Py_ssize_t i = 0; i < batch * n; i++) {
        float *row = out + i * size, *features = row + channels * area;
        int64_t r = pos[2 * i], c = pos[2 * i + 1], action = last_action[i];
        if (present[i]) {
            if (r < 0 || c < 0 || r > SHAPE(a[0], 1) - win || c > wp - win) {
                PyErr_Format(PyExc_IndexError, "observe: agent %zd at (%lld, %lld) sees past "
                             "the padded codes", i % n, (long long)r, (long long)c);
                goto done;
            }
            Py_ssize_t base = (i / n) * plane + (Py_ssize_t)(r * wp + c);
            for (Py_ssize_t y = 0; y < win; y++)  /* a local copy: the stores cannot alias it */
                memcpy(window + y * win, codes + base + y * wp, (size_t)win);
            window[center] &= (uint8_t)~own_bit;
            for (Py_ssize_t ch = 0; ch < channels; ch++) {
                uint8_t bit = bits[ch];
                float *plane = row + ch * area;
                for (Py_ssize_t k = 0; k < area; k++) plane[k] = (window[k] & bit) != 0;
            }
        } else {
            memset(row, 0, sizeof(float) * (size_t)(channels * area));
        }
        features[0] = (float)((double)r / (double)row_scale);
        features[1] = (float)((double)c / (double)col_scale);
        for (Py_ssize_t k = 0; k < actions; k++) features[2 + k] = action == k;
        features[2 + actions] = last_reward[i];
        if (!present[i])  /* as numpy's out *= present: x * 0 keeps the sign of x */
            for (Py_ssize_t k = 0; k < 3 + actions; k++) features[k] *= 0.0f;
    }
    result = Py_NewRef(Py_None);
done:
    release(a, 7);
    return result;
}

/* ---------------------------------------------------------------- cells of a mapping */

static PyObject *gather_cells(PyObject *self, PyObject *args) {
    PyObject *mapping, *keys_o, *rows_o, *out_o;
    if (!PyArg_ParseTuple(args, "OOOO:gather_cells", &mapping, &keys_o, &rows_o, &out_o))
        return NULL;
    PyObject *keys = PySequence_Fast(keys_o, "gather_cells: keys must be a sequence");
    if (!keys) return NULL;
    Array a[2];
    memset(a, 0, sizeof a);
    PyObject *result = NULL;
    if (take(rows_o, &a[0], "rows", I64, 1, 0) || take(out_o, &a[1], "out", I64, 2, 1)) goto done;
    Py_ssize_t n = PySequence_Fast_GET_SIZE(keys), slots = SHAPE(a[1], 0);
    if (SHAPE(a[0], 0) != n || SHAPE(a[1], 1) != 2) {
        PyErr_SetString(PyExc_ValueError, "gather_cells: one row per key, cells as pairs");
        goto done;
    }
    const int64_t *rows = a[0].view.buf;
    int64_t *out = a[1].view.buf;
    int is_dict = PyDict_CheckExact(mapping);
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *key = PySequence_Fast_GET_ITEM(keys, i), *cell;
        if (is_dict) {
            cell = PyDict_GetItemWithError(mapping, key);
            if (!cell) {
                if (!PyErr_Occurred()) PyErr_SetObject(PyExc_KeyError, key);
                goto done;
            }
            Py_INCREF(cell);
        } else if (!(cell = PyObject_GetItem(mapping, key))) {
            goto done;
        }
        PyObject *pair = PySequence_Fast(cell, "gather_cells: a cell is a (row, col) pair");
        Py_DECREF(cell);
        if (!pair) goto done;
        long long row = -1, col = -1;
        if (PySequence_Fast_GET_SIZE(pair) != 2)
            PyErr_SetString(PyExc_ValueError, "gather_cells: a cell is a (row, col) pair");
        else if ((row = PyLong_AsLongLong(PySequence_Fast_GET_ITEM(pair, 0))) != -1 ||
                 !PyErr_Occurred())
            col = PyLong_AsLongLong(PySequence_Fast_GET_ITEM(pair, 1));
        Py_DECREF(pair);
        if (PyErr_Occurred()) goto done;
        if (rows[i] < 0 || rows[i] >= slots) {
            PyErr_SetString(PyExc_IndexError, "gather_cells: a row past the output");
            goto done;
        }
        out[2 * rows[i]] = row;
        out[2 * rows[i] + 1] = col;
    }
    result = Py_NewRef(Py_None);
done:
    release(a, 2);
    Py_DECREF(keys);
    return result;
}

/* ---------------------------------------------------------------- module */

static PyMethodDef methods[] = {
    {"nearest", nearest, METH_VARARGS,
     "nearest(pos, present, out): each agent's nearest agents, see udan.envs.grouping."},
    {"leaders", leaders, METH_VARARGS,
     "leaders(prob, present, threshold, out) -> count: see udan.envs.grouping.form_groups."},
    {"round_order", round_order, METH_VARARGS,
     "round_order(groups, order, sizes) -> rounds: bridge rounds, see udan.envs.grouping."},
    {"resolve_moves", resolve_moves, METH_VARARGS,
     "resolve_moves(pos, actions, passable, present, out): see udan.envs.rules."},
    {"filter_moves", filter_moves, METH_VARARGS,
     "filter_moves(layout, pos, actions, expected, others, free, stop, commands, blocked, "
     "stopped, dest): see udan.edge.safety."},
    {"gather_cells", gather_cells, METH_VARARGS,
     "gather_cells(mapping, keys, rows, out): out[rows[i]] = mapping[keys[i]], (row, col) "
     "pairs; see udan.edge.decide."},
    {"task_rewards", task_rewards, METH_VARARGS,
     "task_rewards(find_water, layout, pos, present, target, t, water, out): see "
     "udan.envs.arena."},
    {"scene_codes", scene_codes, METH_VARARGS,
     "scene_codes(padded_layout, pos, present, target, view, agent_bit, target_bit, out): see "
     "udan.envs.arena."},
    {"observe", observe, METH_VARARGS,
     "observe(codes, pos, last_action, last_reward, present, bits, view, own_bit, row_scale, "
     "col_scale, out): see udan.envs.observe."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "udan._kernels",
    "The grid world's, grouping's and observation's loops in C (see udan/_kernels.c).", -1,
    methods,
};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }
