/*
 * motion._speedups: the optional C accelerator of the control cycle's hot path (issue 12). Each piece is the C twin
 * of Python code that stays the reference and the fallback (the package builds and runs without this module; the
 * tests compare the two on every input they use):
 *
 * SlotBuilder, the C half of motion.protocol.compiled.frozen_builder. A SlotBuilder(cls, names) is a callable that
 * builds an instance of a slotted class from positional values, one per name, without running __init__: it allocates
 * the instance and stores each value in the slot the class's member descriptor of that name points at. That is what
 * the pure-Python builder does with object.__new__ and one descriptor __set__ per field (about 230 ns for a five-field
 * message on the machines of bench/README.md); here it is one call (about 30 ns). Frozen dataclasses refuse assignment
 * in their __setattr__, which neither builder calls: the result is the object the class's own __init__ would build
 * from the same values. What a builder accepts is checked once, when it is made: a class whose instances have no
 * variable part, and for each name an object slot (a member descriptor of type Py_T_OBJECT_EX, writable) of that class
 * or one of its bases. Anything else raises TypeError. A call checks the number of values (TypeError otherwise).
 *
 * CLayout, CanRequestEncoder and CanReplyDecoder, the CAN codec's fast path: one CLayout per layout of the table
 * (handed over by motion.protocol.compiled.native_layout), and can_frame.encode_request / decode_reply on top of them;
 * anything unusual goes to the Python function they were given (see the codec section below).
 *
 * StateAbsorber, the loop of motion.control.axes.AxisStates.absorb (a cycle's replies into the axes' arrays), and
 * stack_rows, the copy of a published snapshot's rows (motion.control.snapshot.frozen).
 *
 * chase, moved_beyond, torque_advance and torque_law, the C twins of the tracking model's numpy steps
 * (motion.control.tracking: the drives' position-loop model and the torque-mode PD model, stepped every cycle), and
 * torque_pd and torque_currents, the torque-mode set-points (motion.control.controller: the PD, and the current limit
 * of motion.transmission): the same floating-point operations in the same order per joint, so the results are the
 * Python version's to the bit (NaN propagation of numpy's minimum / maximum included; built without contraction of
 * a * b + c, see pyproject.toml). The one exception: torque_law's two matrix-vector products sum in index order,
 * where numpy's np.dot sums as its BLAS does (their last bits may differ, as they do between BLAS builds).
 *
 * Exit plan: none upstream; this is our own code, optional by design.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <structmember.h>
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#ifndef Py_T_OBJECT_EX
#define Py_T_OBJECT_EX T_OBJECT_EX
#endif
#ifndef Py_READONLY
#define Py_READONLY READONLY
#endif

typedef struct {
    PyObject_VAR_HEAD
    vectorcallfunc vectorcall;
    PyTypeObject *cls;
    PyObject *names;
    Py_ssize_t offsets[1]; /* ob_size of them: where each value goes in an instance */
} SlotBuilder;

static PyObject *
builder_call(PyObject *self, PyObject *const *args, size_t nargsf, PyObject *kwnames)
{
    SlotBuilder *b = (SlotBuilder *)self;
    if (b->cls == NULL) { /* cleared by the garbage collector while a finalizer still held it */
        PyErr_SetString(PyExc_RuntimeError, "a cleared SlotBuilder");
        return NULL;
    }
    Py_ssize_t n = Py_SIZE(b);
    Py_ssize_t given = PyVectorcall_NARGS(nargsf);
    if (given != n || (kwnames != NULL && PyTuple_GET_SIZE(kwnames) != 0)) {
        PyErr_Format(PyExc_TypeError, "the builder of %s takes %zd positional values, got %zd%s", b->cls->tp_name, n,
                     given, kwnames != NULL && PyTuple_GET_SIZE(kwnames) != 0 ? " and keywords" : "");
        return NULL;
    }
    PyObject *instance = b->cls->tp_alloc(b->cls, 0); /* zero-filled: every slot starts empty */
    if (instance == NULL) {
        return NULL;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject **slot = (PyObject **)((char *)instance + b->offsets[i]);
        PyObject *old = *slot; /* NULL, unless a name is given twice */
        *slot = Py_NewRef(args[i]);
        Py_XDECREF(old);
    }
    return instance;
}

/* The object references each type holds, listed once for its traverse and its clear (APPLY: Py_VISIT or Py_CLEAR). */
#define BUILDER_REFERENCES(APPLY, b) \
    APPLY((b)->cls);                 \
    APPLY((b)->names);

static int
builder_traverse(PyObject *self, visitproc visit, void *arg)
{
    BUILDER_REFERENCES(Py_VISIT, (SlotBuilder *)self)
    return 0;
}

static int
builder_clear(PyObject *self)
{
    BUILDER_REFERENCES(Py_CLEAR, (SlotBuilder *)self)
    return 0;
}

static void
builder_dealloc(PyObject *self)
{
    PyObject_GC_UnTrack(self);
    builder_clear(self);
    Py_TYPE(self)->tp_free(self);
}

static PyObject *
builder_repr(PyObject *self)
{
    SlotBuilder *b = (SlotBuilder *)self;
    if (b->cls == NULL || b->names == NULL) {
        return PyUnicode_FromString("<SlotBuilder (cleared)>");
    }
    return PyUnicode_FromFormat("<SlotBuilder of %s: %R>", b->cls->tp_name, b->names);
}

/* The offset of the object slot ``name`` of ``cls``, or -1 with TypeError set. */
static Py_ssize_t
slot_offset(PyTypeObject *cls, PyObject *name)
{
    if (!PyUnicode_Check(name)) {
        PyErr_Format(PyExc_TypeError, "slot names must be str, got %R", name);
        return -1;
    }
    PyObject *descriptor = PyObject_GetAttr((PyObject *)cls, name); /* a member descriptor is its own class value */
    if (descriptor == NULL) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s has no slot %R", cls->tp_name, name);
        return -1;
    }
    Py_ssize_t offset = -1;
    if (!Py_IS_TYPE(descriptor, &PyMemberDescr_Type)) {
        PyErr_Format(PyExc_TypeError, "%s.%U is not a slot (a %s)", cls->tp_name, name, Py_TYPE(descriptor)->tp_name);
    }
    else {
        PyMemberDescrObject *member = (PyMemberDescrObject *)descriptor;
        PyMemberDef *def = member->d_member;
        if (!PyType_IsSubtype(cls, PyDescr_TYPE(member))) {
            PyErr_Format(PyExc_TypeError, "%s.%U is a slot of another class", cls->tp_name, name);
        }
        else if (def->type != Py_T_OBJECT_EX || (def->flags & Py_READONLY) || def->offset <= 0 ||
                 (size_t)def->offset + sizeof(PyObject *) > (size_t)cls->tp_basicsize) {
            PyErr_Format(PyExc_TypeError, "%s.%U is not a writable object slot", cls->tp_name, name);
        }
        else {
            offset = def->offset;
        }
    }
    Py_DECREF(descriptor);
    return offset;
}

static PyObject *
builder_new(PyTypeObject *type, PyObject *args, PyObject *kwargs)
{
    PyObject *cls;
    PyObject *names;
    static char *keywords[] = {"cls", "names", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "O!O!:SlotBuilder", keywords, &PyType_Type, &cls, &PyTuple_Type,
                                     &names)) {
        return NULL;
    }
    PyTypeObject *target = (PyTypeObject *)cls;
    if (target->tp_itemsize != 0 || target->tp_alloc == NULL) {
        PyErr_Format(PyExc_TypeError, "%s instances have a variable size: no slot builder", target->tp_name);
        return NULL;
    }
    Py_ssize_t n = PyTuple_GET_SIZE(names);
    SlotBuilder *b = PyObject_GC_NewVar(SlotBuilder, type, n);
    if (b == NULL) {
        return NULL;
    }
    b->vectorcall = builder_call;
    b->cls = (PyTypeObject *)Py_NewRef(cls);
    b->names = Py_NewRef(names);
    for (Py_ssize_t i = 0; i < n; i++) {
        b->offsets[i] = slot_offset(target, PyTuple_GET_ITEM(names, i));
        if (b->offsets[i] < 0) {
            Py_DECREF(b);
            return NULL;
        }
    }
    PyObject_GC_Track(b);
    return (PyObject *)b;
}

static PyMemberDef builder_members[] = {
    {"cls", Py_T_OBJECT_EX, offsetof(SlotBuilder, cls), Py_READONLY, "the class built"},
    {"names", Py_T_OBJECT_EX, offsetof(SlotBuilder, names), Py_READONLY, "the slots set, in argument order"},
    {NULL},
};

static PyTypeObject SlotBuilderType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "motion._speedups.SlotBuilder",
    .tp_doc = PyDoc_STR("SlotBuilder(cls, names): builds cls from one positional value per slot name, "
                        "without __init__."),
    .tp_basicsize = offsetof(SlotBuilder, offsets),
    .tp_itemsize = sizeof(Py_ssize_t),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC | Py_TPFLAGS_HAVE_VECTORCALL,
    .tp_new = builder_new,
    .tp_dealloc = builder_dealloc,
    .tp_traverse = builder_traverse,
    .tp_clear = builder_clear,
    .tp_repr = builder_repr,
    .tp_call = PyVectorcall_Call,
    .tp_vectorcall_offset = offsetof(SlotBuilder, vectorcall),
    .tp_members = builder_members,
};

/* ------------------------------------------------------------------------------------------------------ chase */

/* numpy's minimum and maximum of two doubles: a NaN in either gives NaN (the first NaN). */
static inline double
np_minimum(double a, double b)
{
    return (a <= b || isnan(a)) ? a : b;
}

static inline double
np_maximum(double a, double b)
{
    return (a >= b || isnan(a)) ? a : b;
}

/* What a one-dimensional buffer holds, by its struct format: float64, int64 (numpy's intp on LP64 and LLP64
   platforms) or bool. */
typedef enum { KIND_FLOAT64, KIND_INT64, KIND_BOOL } BufferKind;

static const char *const kind_names[] = {"float64", "int64", "bool"};

static int
holds(const Py_buffer *view, BufferKind kind)
{
    const char *format = view->format;
    if (format == NULL || view->ndim != 1) {
        return 0;
    }
    switch (kind) {
    case KIND_FLOAT64:
        return view->itemsize == 8 && strcmp(format, "d") == 0;
    case KIND_INT64:
        return view->itemsize == 8 && (strcmp(format, "l") == 0 || strcmp(format, "q") == 0);
    default:
        return view->itemsize == 1 && strcmp(format, "?") == 0;
    }
}

/* A C-contiguous one-dimensional buffer of ``kind`` and n entries (n < 0: take its length), or -1 with the error set. */
static int
take_buffer(const char *function, PyObject *obj, Py_buffer *view, int writable, BufferKind kind, const char *name,
            Py_ssize_t *n)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0) {
        PyErr_Format(PyExc_TypeError, "%s: %s must be a C-contiguous%s %s array", function, name,
                     writable ? ", writable" : "", kind_names[kind]);
        return -1;
    }
    if (!holds(view, kind)) {
        PyErr_Format(PyExc_TypeError, "%s: %s must be a one-dimensional %s array", function, name, kind_names[kind]);
        PyBuffer_Release(view);
        return -1;
    }
    Py_ssize_t length = view->len / view->itemsize;
    if (*n >= 0 && length != *n) {
        PyErr_Format(PyExc_ValueError, "%s: %s has %zd entries, the first array %zd", function, name, length, *n);
        PyBuffer_Release(view);
        return -1;
    }
    *n = length;
    return 0;
}

/* take_buffer of a float64 array. */
static int
take_array(const char *function, PyObject *obj, Py_buffer *view, int writable, const char *name, Py_ssize_t *n)
{
    return take_buffer(function, obj, view, writable, KIND_FLOAT64, name, n);
}

/* The ``count`` float64 arrays of one length first among a call's ``nargs`` arguments (``expected`` of them; see
   take_array), the first ``writable_count`` writable; released by release_arrays. -1 with the error set. */
static int
take_arrays(const char *function, PyObject *const *objects, Py_ssize_t nargs, Py_ssize_t expected,
            const char *const *names, int writable_count, int count, Py_buffer *views, Py_ssize_t *n)
{
    if (nargs != expected) {
        PyErr_Format(PyExc_TypeError, "%s takes %zd positional arguments, got %zd", function, expected, nargs);
        return -1;
    }
    *n = -1;
    for (int taken = 0; taken < count; taken++) {
        if (take_array(function, objects[taken], &views[taken], taken < writable_count, names[taken], n) < 0) {
            for (int i = 0; i < taken; i++) {
                PyBuffer_Release(&views[i]);
            }
            return -1;
        }
    }
    return 0;
}

static void
release_arrays(Py_buffer *views, int count)
{
    for (int i = 0; i < count; i++) {
        PyBuffer_Release(&views[i]);
    }
}

#define CHASE_ARRAYS 6

static PyObject *
chase(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    /* chase(x, v, dt, target, cap, gain, accel, max_step) */
    if (nargs != 8) {
        PyErr_Format(PyExc_TypeError, "chase takes 8 positional arguments (x, v, dt, target, cap, gain, accel, "
                     "max_step), got %zd", nargs);
        return NULL;
    }
    double dt = PyFloat_AsDouble(args[2]);
    if (dt == -1.0 && PyErr_Occurred()) {
        return NULL;
    }
    double max_step = PyFloat_AsDouble(args[7]);
    if (max_step == -1.0 && PyErr_Occurred()) {
        return NULL;
    }
    if (!(max_step > 0.0) || !isfinite(dt) || dt / max_step > 1e9) {
        PyErr_SetString(PyExc_ValueError, "chase: max_step must be > 0 and dt finite, at most 1e9 steps");
        return NULL;
    }
    static const char *names[CHASE_ARRAYS] = {"x", "v", "target", "cap", "gain", "accel"};
    PyObject *objects[CHASE_ARRAYS] = {args[0], args[1], args[3], args[4], args[5], args[6]};
    Py_buffer views[CHASE_ARRAYS];
    Py_ssize_t n;
    if (take_arrays("chase", objects, CHASE_ARRAYS, CHASE_ARRAYS, names, 2, CHASE_ARRAYS, views, &n) < 0) {
        return NULL;
    }
    {
        double *x = views[0].buf, *v = views[1].buf;
        const double *target = views[2].buf, *cap = views[3].buf, *gain = views[4].buf, *accel = views[5].buf;
        /* as the Python: steps = max(1, ceil(dt / MAX_STEP_S - 1e-9)); h = dt / steps */
        double steps_f = ceil(dt / max_step - 1e-9);
        long long steps = steps_f < 1.0 ? 1 : (long long)steps_f;
        double h = dt / (double)steps;
        for (Py_ssize_t i = 0; i < n; i++) {
            double xi = x[i], vi = v[i];
            double two_accel = accel[i] * 2.0, slew = accel[i] * h, no_slew = -slew;
            for (long long k = 0; k < steps; k++) {
                double e = target[i] - xi;
                double s = fabs(e);
                double w = sqrt(s * two_accel); /* braking curve: sqrt(2 a |e|) */
                s *= gain[i];
                s = np_minimum(s, w);
                s = np_minimum(s, cap[i]);
                s = copysign(s, e); /* the speed the drive asks for */
                w = np_maximum(np_minimum(s - vi, slew), no_slew);
                vi += w;
                xi += vi * h;
            }
            x[i] = xi;
            v[i] = vi;
        }
    }
    release_arrays(views, CHASE_ARRAYS);
    Py_RETURN_NONE;
}

/* ------------------------------------------------------------------------------------------------------ codec */

/*
 * The CAN codec's fast path in C: the twin of the encoders and decoders motion.protocol.compiled generates from the
 * table, one CLayout per layout (made from the table by the Python side, checked once here), and the two public CAN
 * calls built on them (CanRequestEncoder: can_frame.encode_request; CanReplyDecoder: can_frame.decode_reply). Like
 * the Python fast path they never decide an error: anything unusual (a value of another type, out of range, not
 * finite; an odd id or payload; a command without a layout) goes to the Python function given as ``fallback``, which
 * gives the same result or raises the same error.
 */

enum { KIND_INT = 0, KIND_REAL = 1, KIND_ENUM = 2, KIND_FLAGS = 3 };

/* Largest magnitude of a raw value times its scale numerator that a double holds exactly (2^53). */
#define EXACT_DOUBLE_INT 9007199254740992LL
#define MAX_PAYLOAD 64
#define MAX_VALUES 32

typedef struct {
    PyObject *name; /* the message attribute */
    int kind;
    long long num, den; /* physical = raw * num / den */
    long long lo, hi;   /* the valid raw range */
    Py_ssize_t offset;  /* in the payload */
    int width;          /* 1, 2 or 4 bytes, little-endian */
    int is_signed;
    PyObject *enum_cls; /* ENUM / FLAGS: the class an encoded value must be exactly; else NULL */
    PyObject *members;  /* ENUM / FLAGS: value -> member (decode); else NULL */
} FieldSpec;

typedef struct {
    PyObject_HEAD
    int command;          /* the command byte at payload[0], or -1 (none: RS485 data, the 0x280 frame) */
    Py_ssize_t size;      /* payload bytes */
    Py_ssize_t nfields;
    FieldSpec *fields;
    PyObject *uncarried;  /* names that must be None for the fast path to encode */
    PyObject *builder;    /* builds the message from nvalues values; None: no decode */
    Py_ssize_t nvalues;
    Py_ssize_t *sources;  /* per builder value: the field's index, or -1 for constants[i] */
    PyObject *constants;  /* tuple of nvalues */
    PyObject *value_key;  /* "_value_" */
} CLayout;

static PyTypeObject CLayoutType;

#define CLAYOUT_REFERENCES(APPLY, L)                   \
    for (Py_ssize_t i = 0; i < (L)->nfields; i++) {    \
        APPLY((L)->fields[i].name);                    \
        APPLY((L)->fields[i].enum_cls);                \
        APPLY((L)->fields[i].members);                 \
    }                                                  \
    APPLY((L)->uncarried);                             \
    APPLY((L)->builder);                               \
    APPLY((L)->constants);                             \
    APPLY((L)->value_key);

static int
clayout_traverse(PyObject *self, visitproc visit, void *arg)
{
    CLAYOUT_REFERENCES(Py_VISIT, (CLayout *)self)
    return 0;
}

static int
clayout_clear(PyObject *self)
{
    CLAYOUT_REFERENCES(Py_CLEAR, (CLayout *)self)
    return 0;
}

static void
clayout_dealloc(PyObject *self)
{
    CLayout *L = (CLayout *)self;
    PyObject_GC_UnTrack(self);
    clayout_clear(self);
    PyMem_Free(L->fields);
    PyMem_Free(L->sources);
    Py_TYPE(self)->tp_free(self);
}

static int
field_from_tuple(FieldSpec *f, PyObject *spec, Py_ssize_t size)
{
    PyObject *name, *enum_cls, *members;
    int kind, is_signed, width;
    long long num, den, lo, hi;
    Py_ssize_t offset;
    if (!PyTuple_Check(spec) || !PyArg_ParseTuple(spec, "UiLLLLnipOO;a field: (name, kind, num, den, lo, hi, offset, "
                                                  "width, signed, enum class, members)", &name, &kind, &num, &den, &lo,
                                                  &hi, &offset, &width, &is_signed, &enum_cls, &members)) {
        if (!PyErr_Occurred()) {
            PyErr_SetString(PyExc_TypeError, "a field must be a tuple");
        }
        return -1;
    }
    if (kind < KIND_INT || kind > KIND_FLAGS) {
        PyErr_Format(PyExc_ValueError, "field %U: kind %d is not 0..3", name, kind);
        return -1;
    }
    if (width != 1 && width != 2 && width != 4) {
        PyErr_Format(PyExc_ValueError, "field %U: width %d is not 1, 2 or 4", name, width);
        return -1;
    }
    long long type_lo = is_signed ? -(1LL << (8 * width - 1)) : 0;
    long long type_hi = is_signed ? (1LL << (8 * width - 1)) - 1 : (1LL << (8 * width)) - 1;
    if (offset < 0 || offset + width > size || lo > hi || lo < type_lo || hi > type_hi || num < 1 || den < 1 ||
        num > (1LL << 20) || den > (1LL << 40)) {
        PyErr_Format(PyExc_ValueError, "field %U: offset, range or scale out of bounds", name);
        return -1;
    }
    int is_enum = kind == KIND_ENUM || kind == KIND_FLAGS;
    if (is_enum && (!PyType_Check(enum_cls) || !PyDict_Check(members))) {
        PyErr_Format(PyExc_TypeError, "field %U: an enum field needs its class and a dict of its members", name);
        return -1;
    }
    f->name = Py_NewRef(name);
    f->kind = kind;
    f->num = num;
    f->den = den;
    f->lo = lo;
    f->hi = hi;
    f->offset = offset;
    f->width = width;
    f->is_signed = is_signed;
    f->enum_cls = is_enum ? Py_NewRef(enum_cls) : NULL;
    f->members = is_enum ? Py_NewRef(members) : NULL;
    return 0;
}

static PyObject *
clayout_new(PyTypeObject *type, PyObject *args, PyObject *kwargs)
{
    int command;
    Py_ssize_t size;
    PyObject *fields, *uncarried, *builder, *sources, *constants;
    static char *keywords[] = {"command", "size", "fields", "uncarried", "builder", "sources", "constants", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "inO!O!OO!O!:CLayout", keywords, &command, &size, &PyTuple_Type,
                                     &fields, &PyTuple_Type, &uncarried, &builder, &PyTuple_Type, &sources,
                                     &PyTuple_Type, &constants)) {
        return NULL;
    }
    if (command < -1 || command > 255 || size < 1 || size > MAX_PAYLOAD) {
        PyErr_Format(PyExc_ValueError, "CLayout: command %d or size %zd out of range", command, size);
        return NULL;
    }
    Py_ssize_t nfields = PyTuple_GET_SIZE(fields), nvalues = PyTuple_GET_SIZE(sources);
    if (nfields > MAX_VALUES || nvalues > MAX_VALUES || PyTuple_GET_SIZE(constants) != nvalues ||
        (builder != Py_None && !PyCallable_Check(builder))) {
        PyErr_SetString(PyExc_ValueError, "CLayout: too many fields, or sources and constants of different lengths, "
                                          "or a builder that is not callable");
        return NULL;
    }
    CLayout *L = PyObject_GC_New(CLayout, type);
    if (L == NULL) {
        return NULL;
    }
    L->command = command;
    L->size = size;
    L->nfields = 0;
    L->fields = PyMem_Calloc(nfields ? nfields : 1, sizeof(FieldSpec));
    L->sources = PyMem_Calloc(nvalues ? nvalues : 1, sizeof(Py_ssize_t));
    L->uncarried = Py_NewRef(uncarried);
    L->builder = builder == Py_None ? NULL : Py_NewRef(builder);
    L->nvalues = nvalues;
    L->constants = Py_NewRef(constants);
    L->value_key = PyUnicode_InternFromString("_value_");
    if (L->fields == NULL || L->sources == NULL || L->value_key == NULL) {
        Py_DECREF(L);
        return PyErr_Occurred() ? NULL : PyErr_NoMemory();
    }
    for (Py_ssize_t i = 0; i < nfields; i++) {
        if (field_from_tuple(&L->fields[i], PyTuple_GET_ITEM(fields, i), size) < 0) {
            Py_DECREF(L);
            return NULL;
        }
        L->nfields = i + 1;
    }
    for (Py_ssize_t i = 0; i < PyTuple_GET_SIZE(uncarried); i++) {
        if (!PyUnicode_Check(PyTuple_GET_ITEM(uncarried, i))) {
            PyErr_SetString(PyExc_TypeError, "CLayout: uncarried names must be str");
            Py_DECREF(L);
            return NULL;
        }
    }
    for (Py_ssize_t i = 0; i < nvalues; i++) {
        Py_ssize_t source = PyLong_AsSsize_t(PyTuple_GET_ITEM(sources, i));
        if ((source == -1 && PyErr_Occurred()) || source < -1 || source >= nfields) {
            PyErr_Clear();
            PyErr_Format(PyExc_ValueError, "CLayout: source %zd is neither -1 nor a field index", i);
            Py_DECREF(L);
            return NULL;
        }
        L->sources[i] = source;
    }
    PyObject_GC_Track(L);
    return (PyObject *)L;
}

/* An attribute of ``o``: a new reference; NULL with no error set for "take the Python path" (AttributeError). */
static PyObject *
get_attribute(PyObject *o, PyObject *name)
{
    PyObject *value = PyObject_GetAttr(o, name);
    if (value == NULL && PyErr_ExceptionMatches(PyExc_AttributeError)) {
        PyErr_Clear();
    }
    return value;
}

/* The payload of ``message`` into ``buffer`` (L->size bytes): 1 done, 0 take the Python path, -1 error set. */
static int
encode_payload(CLayout *L, PyObject *message, unsigned char *buffer)
{
    memset(buffer, 0, (size_t)L->size);
    if (L->command >= 0) {
        buffer[0] = (unsigned char)L->command;
    }
    for (Py_ssize_t i = 0; i < PyTuple_GET_SIZE(L->uncarried); i++) {
        PyObject *value = get_attribute(message, PyTuple_GET_ITEM(L->uncarried, i));
        if (value == NULL) {
            return PyErr_Occurred() ? -1 : 0;
        }
        Py_DECREF(value);
        if (value != Py_None) {
            return 0;
        }
    }
    for (Py_ssize_t i = 0; i < L->nfields; i++) {
        FieldSpec *f = &L->fields[i];
        PyObject *value = get_attribute(message, f->name);
        if (value == NULL) {
            return PyErr_Occurred() ? -1 : 0;
        }
        long long raw = 0;
        int usable = 0;
        if (f->kind == KIND_INT) {
            if (PyLong_CheckExact(value)) {
                int overflow = 0;
                raw = PyLong_AsLongLongAndOverflow(value, &overflow);
                usable = !overflow && !(raw == -1 && PyErr_Occurred());
            }
        }
        else if (f->kind == KIND_REAL) {
            /* as the Python: round(value * den / num), half to even, for a float only */
            if (PyFloat_CheckExact(value)) {
                double x = PyFloat_AS_DOUBLE(value);
                if (f->den != 1) {
                    x = x * (double)f->den;
                }
                if (f->num != 1) {
                    x = x / (double)f->num;
                }
                if (isfinite(x) && x > -9.0e18 && x < 9.0e18) {
                    raw = (long long)rint(x);
                    usable = 1;
                }
            }
        }
        else if (Py_IS_TYPE(value, (PyTypeObject *)f->enum_cls)) {
            PyObject *number = get_attribute(value, L->value_key);
            if (number == NULL) {
                Py_DECREF(value);
                return PyErr_Occurred() ? -1 : 0;
            }
            if (PyLong_Check(number)) {
                int overflow = 0;
                raw = PyLong_AsLongLongAndOverflow(number, &overflow);
                usable = !overflow && !(raw == -1 && PyErr_Occurred());
            }
            Py_DECREF(number);
        }
        Py_DECREF(value);
        if (PyErr_Occurred()) {
            return -1;
        }
        if (!usable || raw < f->lo || raw > f->hi) {
            return 0;
        }
        unsigned long long bits = (unsigned long long)raw;
        for (int b = 0; b < f->width; b++) {
            buffer[f->offset + b] = (unsigned char)(bits >> (8 * b));
        }
    }
    return 1;
}

/* The message of ``payload`` (L->size bytes): a new reference; NULL with no error set: take the Python path. */
static PyObject *
decode_payload(CLayout *L, const unsigned char *payload)
{
    if (L->builder == NULL) {
        return NULL;
    }
    PyObject *values[MAX_VALUES];
    Py_ssize_t made = 0;
    PyObject *result = NULL;
    for (; made < L->nfields; made++) {
        FieldSpec *f = &L->fields[made];
        unsigned long long bits = 0;
        for (int b = f->width - 1; b >= 0; b--) {
            bits = (bits << 8) | payload[f->offset + b];
        }
        long long raw = (long long)bits;
        if (f->is_signed && (bits >> (8 * f->width - 1)) & 1) {
            raw -= 1LL << (8 * f->width);
        }
        if (raw < f->lo || raw > f->hi) {
            goto done;
        }
        PyObject *value = NULL;
        if (f->kind == KIND_INT) {
            value = PyLong_FromLongLong(raw);
        }
        else if (f->kind == KIND_REAL) {
            /* as the Python: raw * num / den, the product exact, the quotient correctly rounded */
            long long product = raw * f->num;
            if (product >= EXACT_DOUBLE_INT || product <= -EXACT_DOUBLE_INT) {
                goto done;
            }
            value = PyFloat_FromDouble((double)product / (double)f->den);
        }
        else {
            PyObject *key = PyLong_FromLongLong(raw);
            if (key == NULL) {
                goto done;
            }
            value = PyDict_GetItemWithError(f->members, key);
            if (value != NULL) {
                Py_INCREF(value);
            }
            else if (!PyErr_Occurred() && f->kind == KIND_FLAGS) {
                value = PyObject_CallOneArg(f->enum_cls, key); /* a combination not seen before */
            }
            Py_DECREF(key);
        }
        if (value == NULL) {
            goto done;
        }
        values[made] = value;
    }
    PyObject *arguments[MAX_VALUES];
    for (Py_ssize_t i = 0; i < L->nvalues; i++) {
        Py_ssize_t source = L->sources[i];
        arguments[i] = source >= 0 ? values[source] : PyTuple_GET_ITEM(L->constants, i);
    }
    result = PyObject_Vectorcall(L->builder, arguments, (size_t)L->nvalues, NULL);
done:
    for (Py_ssize_t i = 0; i < made; i++) {
        Py_DECREF(values[i]);
    }
    return result;
}

/* Whether a garbage collector's clear has emptied ``L`` (a finalizer may still call it): RuntimeError set. */
static int
clayout_cleared(CLayout *L)
{
    if (L->uncarried == NULL || L->constants == NULL || L->value_key == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "a cleared CLayout");
        return 1;
    }
    return 0;
}

static PyObject *
clayout_encode(PyObject *self, PyObject *message)
{
    CLayout *L = (CLayout *)self;
    if (clayout_cleared(L)) {
        return NULL;
    }
    unsigned char buffer[MAX_PAYLOAD];
    int done = encode_payload(L, message, buffer);
    if (done < 0) {
        return NULL;
    }
    if (done == 0) {
        Py_RETURN_NONE;
    }
    return PyBytes_FromStringAndSize((const char *)buffer, L->size);
}

static PyObject *
clayout_decode(PyObject *self, PyObject *data)
{
    CLayout *L = (CLayout *)self;
    if (clayout_cleared(L)) {
        return NULL;
    }
    if (!PyBytes_Check(data) || PyBytes_GET_SIZE(data) != L->size) {
        PyErr_Format(PyExc_TypeError, "CLayout.decode takes bytes of the layout's size, %zd", L->size);
        return NULL;
    }
    PyObject *message = decode_payload(L, (const unsigned char *)PyBytes_AS_STRING(data));
    if (message == NULL && !PyErr_Occurred()) {
        Py_RETURN_NONE;
    }
    return message;
}

static PyMethodDef clayout_methods[] = {
    {"encode", clayout_encode, METH_O, PyDoc_STR("encode(message) -> payload bytes, or None: take the Python path")},
    {"decode", clayout_decode, METH_O, PyDoc_STR("decode(payload) -> message, or None: take the Python path")},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject CLayoutType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "motion._speedups.CLayout",
    .tp_doc = PyDoc_STR("CLayout(command, size, fields, uncarried, builder, sources, constants): one layout of the "
                        "table, encoded and decoded in C (see motion.protocol.compiled)."),
    .tp_basicsize = sizeof(CLayout),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_new = clayout_new,
    .tp_dealloc = clayout_dealloc,
    .tp_traverse = clayout_traverse,
    .tp_clear = clayout_clear,
    .tp_methods = clayout_methods,
};

/* -- the two public CAN calls -- */

typedef struct {
    PyObject_HEAD
    vectorcallfunc vectorcall;
    PyObject *layouts;  /* encoder: {class: CLayout}; decoder: tuple of 256 (CLayout or None) */
    PyObject *shared;   /* encoder: {class: {command value: CLayout}} (classes with a command field); decoder: NULL */
    PyObject *builder;  /* encoder: builds the frame (arbitration id, data) */
    PyObject *special;  /* encoder: the class sent on special_id (MultiMotorTorque) */
    PyObject *fallback; /* the Python function, called with the same arguments */
    PyObject *command_key; /* "command" */
    PyObject *value_key;   /* "_value_" */
    long id_base, id_min, id_max, special_id;
} CanCodec;

#define CANCODEC_REFERENCES(APPLY, c) \
    APPLY((c)->layouts);              \
    APPLY((c)->shared);               \
    APPLY((c)->builder);              \
    APPLY((c)->special);              \
    APPLY((c)->fallback);             \
    APPLY((c)->command_key);          \
    APPLY((c)->value_key);

static int
cancodec_traverse(PyObject *self, visitproc visit, void *arg)
{
    CANCODEC_REFERENCES(Py_VISIT, (CanCodec *)self)
    return 0;
}

static int
cancodec_clear(PyObject *self)
{
    CANCODEC_REFERENCES(Py_CLEAR, (CanCodec *)self)
    return 0;
}

static void
cancodec_dealloc(PyObject *self)
{
    PyObject_GC_UnTrack(self);
    cancodec_clear(self);
    Py_TYPE(self)->tp_free(self);
}

static PyObject *
take_python_path(CanCodec *c, PyObject *const *args, size_t nargsf, PyObject *kwnames)
{
    return PyObject_Vectorcall(c->fallback, args, nargsf, kwnames);
}

/* Whether a garbage collector's clear has emptied ``c`` (a finalizer may still call it): RuntimeError set. */
static int
cancodec_cleared(CanCodec *c)
{
    if (c->layouts == NULL || c->fallback == NULL || c->command_key == NULL || c->value_key == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "a cleared CAN codec");
        return 1;
    }
    return 0;
}

/* The layout of ``message`` (borrowed), or NULL: none (error set if one happened). */
static CLayout *
layout_of(CanCodec *c, PyObject *message)
{
    PyObject *cls = (PyObject *)Py_TYPE(message);
    PyObject *layout = PyDict_GetItemWithError(c->layouts, cls);
    if (layout != NULL || PyErr_Occurred()) {
        return (CLayout *)layout;
    }
    PyObject *by_command = PyDict_GetItemWithError(c->shared, cls);
    if (by_command == NULL) {
        return NULL;
    }
    PyObject *command = get_attribute(message, c->command_key);
    if (command == NULL) {
        return NULL;
    }
    PyObject *value = get_attribute(command, c->value_key);
    Py_DECREF(command);
    if (value == NULL) {
        return NULL;
    }
    layout = PyDict_GetItemWithError(by_command, value);
    Py_DECREF(value);
    return (CLayout *)layout;
}

/* encode_request(message, motor_id=1) -> CanFrame */
static PyObject *
encoder_call(PyObject *self, PyObject *const *args, size_t nargsf, PyObject *kwnames)
{
    CanCodec *c = (CanCodec *)self;
    if (cancodec_cleared(c)) {
        return NULL;
    }
    Py_ssize_t nargs = PyVectorcall_NARGS(nargsf);
    if (kwnames != NULL || nargs < 1 || nargs > 2) {
        return take_python_path(c, args, nargsf, kwnames);
    }
    long motor_id = c->id_min;
    if (nargs == 2) {
        if (!PyLong_CheckExact(args[1])) {
            return take_python_path(c, args, nargsf, kwnames);
        }
        int overflow = 0;
        motor_id = PyLong_AsLongAndOverflow(args[1], &overflow);
        if (overflow || motor_id < c->id_min || motor_id > c->id_max) {
            PyErr_Clear();
            return take_python_path(c, args, nargsf, kwnames);
        }
    }
    CLayout *layout = layout_of(c, args[0]);
    if (layout == NULL) {
        return PyErr_Occurred() ? NULL : take_python_path(c, args, nargsf, kwnames);
    }
    unsigned char buffer[MAX_PAYLOAD];
    int done = encode_payload(layout, args[0], buffer);
    if (done <= 0) {
        return done < 0 ? NULL : take_python_path(c, args, nargsf, kwnames);
    }
    long arbitration_id = (PyObject *)Py_TYPE(args[0]) == c->special ? c->special_id : c->id_base + motor_id;
    PyObject *parts[2];
    parts[0] = PyLong_FromLong(arbitration_id);
    parts[1] = PyBytes_FromStringAndSize((const char *)buffer, layout->size);
    PyObject *frame = NULL;
    if (parts[0] != NULL && parts[1] != NULL) {
        frame = PyObject_Vectorcall(c->builder, parts, 2, NULL);
    }
    Py_XDECREF(parts[0]);
    Py_XDECREF(parts[1]);
    return frame;
}

/* decode_reply(arbitration_id, data) -> (motor id, message) */
static PyObject *
decoder_call(PyObject *self, PyObject *const *args, size_t nargsf, PyObject *kwnames)
{
    CanCodec *c = (CanCodec *)self;
    if (cancodec_cleared(c)) {
        return NULL;
    }
    Py_ssize_t nargs = PyVectorcall_NARGS(nargsf);
    if (kwnames != NULL || nargs != 2 || !PyLong_CheckExact(args[0]) || !PyBytes_CheckExact(args[1]) ||
        PyBytes_GET_SIZE(args[1]) != 8) {
        return take_python_path(c, args, nargsf, kwnames);
    }
    int overflow = 0;
    long arbitration_id = PyLong_AsLongAndOverflow(args[0], &overflow);
    if (overflow || arbitration_id < c->id_base + c->id_min || arbitration_id > c->id_base + c->id_max) {
        PyErr_Clear();
        return take_python_path(c, args, nargsf, kwnames);
    }
    const unsigned char *payload = (const unsigned char *)PyBytes_AS_STRING(args[1]);
    PyObject *layout = PyTuple_GET_ITEM(c->layouts, payload[0]);
    if (layout == Py_None || ((CLayout *)layout)->size != 8) {
        return take_python_path(c, args, nargsf, kwnames);
    }
    PyObject *message = decode_payload((CLayout *)layout, payload);
    if (message == NULL) {
        return PyErr_Occurred() ? NULL : take_python_path(c, args, nargsf, kwnames);
    }
    PyObject *motor_id = PyLong_FromLong(arbitration_id - c->id_base);
    if (motor_id == NULL) {
        Py_DECREF(message);
        return NULL;
    }
    PyObject *pair = PyTuple_Pack(2, motor_id, message);
    Py_DECREF(motor_id);
    Py_DECREF(message);
    return pair;
}

static PyObject *
cancodec_make(PyTypeObject *type, vectorcallfunc call, PyObject *layouts, PyObject *shared, PyObject *builder,
              PyObject *special, PyObject *fallback, long id_base, long id_min, long id_max, long special_id)
{
    CanCodec *c = PyObject_GC_New(CanCodec, type);
    if (c == NULL) {
        return NULL;
    }
    c->vectorcall = call;
    c->layouts = Py_NewRef(layouts);
    c->shared = Py_XNewRef(shared);
    c->builder = Py_XNewRef(builder);
    c->special = Py_XNewRef(special);
    c->fallback = Py_NewRef(fallback);
    c->command_key = PyUnicode_InternFromString("command");
    c->value_key = PyUnicode_InternFromString("_value_");
    c->id_base = id_base;
    c->id_min = id_min;
    c->id_max = id_max;
    c->special_id = special_id;
    if (c->command_key == NULL || c->value_key == NULL) {
        Py_DECREF(c);
        return NULL;
    }
    PyObject_GC_Track(c);
    return (PyObject *)c;
}

static PyObject *
encoder_new(PyTypeObject *type, PyObject *args, PyObject *kwargs)
{
    PyObject *layouts, *shared, *builder, *special, *fallback;
    long id_base, id_min, id_max, special_id;
    static char *keywords[] = {"layouts", "shared", "frame", "special", "special_id", "id_base", "id_min", "id_max",
                               "fallback", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "O!O!OOllllO:CanRequestEncoder", keywords, &PyDict_Type, &layouts,
                                     &PyDict_Type, &shared, &builder, &special, &special_id, &id_base, &id_min,
                                     &id_max, &fallback)) {
        return NULL;
    }
    if (!PyCallable_Check(builder) || !PyCallable_Check(fallback) || id_min > id_max) {
        PyErr_SetString(PyExc_TypeError, "CanRequestEncoder: frame and fallback must be callable, id_min <= id_max");
        return NULL;
    }
    PyObject *key, *value;
    Py_ssize_t position = 0;
    while (PyDict_Next(layouts, &position, &key, &value)) {
        if (!Py_IS_TYPE(value, &CLayoutType)) {
            PyErr_SetString(PyExc_TypeError, "CanRequestEncoder: layouts maps classes to CLayout");
            return NULL;
        }
    }
    position = 0;
    while (PyDict_Next(shared, &position, &key, &value)) {
        PyObject *k2, *v2;
        Py_ssize_t p2 = 0;
        if (!PyDict_Check(value)) {
            PyErr_SetString(PyExc_TypeError, "CanRequestEncoder: shared maps classes to {command: CLayout}");
            return NULL;
        }
        while (PyDict_Next(value, &p2, &k2, &v2)) {
            if (!Py_IS_TYPE(v2, &CLayoutType)) {
                PyErr_SetString(PyExc_TypeError, "CanRequestEncoder: shared maps classes to {command: CLayout}");
                return NULL;
            }
        }
    }
    return cancodec_make(type, encoder_call, layouts, shared, builder, special, fallback, id_base, id_min, id_max,
                         special_id);
}

static PyObject *
decoder_new(PyTypeObject *type, PyObject *args, PyObject *kwargs)
{
    PyObject *layouts, *fallback;
    long id_base, id_min, id_max;
    static char *keywords[] = {"layouts", "id_base", "id_min", "id_max", "fallback", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "O!lllO:CanReplyDecoder", keywords, &PyTuple_Type, &layouts,
                                     &id_base, &id_min, &id_max, &fallback)) {
        return NULL;
    }
    if (PyTuple_GET_SIZE(layouts) != 256 || !PyCallable_Check(fallback) || id_min > id_max) {
        PyErr_SetString(PyExc_TypeError, "CanReplyDecoder: 256 layouts (CLayout or None), a callable fallback");
        return NULL;
    }
    for (Py_ssize_t i = 0; i < 256; i++) {
        PyObject *layout = PyTuple_GET_ITEM(layouts, i);
        if (layout != Py_None && !Py_IS_TYPE(layout, &CLayoutType)) {
            PyErr_SetString(PyExc_TypeError, "CanReplyDecoder: 256 layouts (CLayout or None), a callable fallback");
            return NULL;
        }
    }
    return cancodec_make(type, decoder_call, layouts, NULL, NULL, NULL, fallback, id_base, id_min, id_max, 0);
}

static PyMemberDef cancodec_members[] = {
    {"fallback", Py_T_OBJECT_EX, offsetof(CanCodec, fallback), Py_READONLY, "the Python function it defers to"},
    {NULL},
};

static PyTypeObject CanRequestEncoderType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "motion._speedups.CanRequestEncoder",
    .tp_doc = PyDoc_STR("encode_request(message, motor_id=1) -> CanFrame, in C (motion.protocol.can_frame)."),
    .tp_basicsize = sizeof(CanCodec),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC | Py_TPFLAGS_HAVE_VECTORCALL,
    .tp_new = encoder_new,
    .tp_dealloc = cancodec_dealloc,
    .tp_traverse = cancodec_traverse,
    .tp_clear = cancodec_clear,
    .tp_call = PyVectorcall_Call,
    .tp_vectorcall_offset = offsetof(CanCodec, vectorcall),
    .tp_members = cancodec_members,
};

static PyTypeObject CanReplyDecoderType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "motion._speedups.CanReplyDecoder",
    .tp_doc = PyDoc_STR("decode_reply(arbitration_id, data) -> (motor id, message), in C "
                        "(motion.protocol.can_frame)."),
    .tp_basicsize = sizeof(CanCodec),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC | Py_TPFLAGS_HAVE_VECTORCALL,
    .tp_new = decoder_new,
    .tp_dealloc = cancodec_dealloc,
    .tp_traverse = cancodec_traverse,
    .tp_clear = cancodec_clear,
    .tp_call = PyVectorcall_Call,
    .tp_vectorcall_offset = offsetof(CanCodec, vectorcall),
    .tp_members = cancodec_members,
};

/* -------------------------------------------------------------------------------------- the torque-mode model */

/* torque_pd(tau, kp, target, x, kd, ref_v, v): tau = kp * (target - x) + (ref_v - v) * kd, in place */
static PyObject *
torque_pd(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    static const char *names[] = {"tau", "kp", "target", "x", "kd", "ref_v", "v"};
    Py_buffer views[7];
    Py_ssize_t n;
    if (take_arrays("torque_pd", args, nargs, 7, names, 1, 7, views, &n) < 0) {
        return NULL;
    }
    double *tau = views[0].buf;
    const double *kp = views[1].buf, *target = views[2].buf, *x = views[3].buf, *kd = views[4].buf;
    const double *ref_v = views[5].buf, *v = views[6].buf;
    for (Py_ssize_t i = 0; i < n; i++) {
        double p = kp[i] * (target[i] - x[i]);
        double d = (ref_v[i] - v[i]) * kd[i];
        tau[i] = p + d;
    }
    release_arrays(views, 7);
    Py_RETURN_NONE;
}

/* moved_beyond(a, b, limit): numpy's abs(a - b).max() > limit (a NaN anywhere: False, as NaN > limit is) */
static PyObject *
moved_beyond(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    static const char *names[] = {"a", "b"};
    Py_buffer views[2];
    Py_ssize_t n;
    if (take_arrays("moved_beyond", args, nargs, 3, names, 0, 2, views, &n) < 0) {
        return NULL;
    }
    double limit = PyFloat_AsDouble(args[2]);
    if (limit == -1.0 && PyErr_Occurred()) {
        release_arrays(views, 2);
        return NULL;
    }
    const double *a = views[0].buf, *b = views[1].buf;
    int beyond = 0, nan = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        double moved = fabs(a[i] - b[i]);
        if (isnan(moved)) {
            nan = 1;
        }
        else if (moved > limit) {
            beyond = 1;
        }
    }
    release_arrays(views, 2);
    return PyBool_FromLong(beyond && !nan);
}

/* A C-contiguous float64 n x n matrix, or -1 with the error set. */
static int
take_matrix(const char *function, PyObject *obj, Py_buffer *view, const char *name, Py_ssize_t n)
{
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
        PyErr_Format(PyExc_TypeError, "%s: %s must be a C-contiguous float64 matrix", function, name);
        return -1;
    }
    if (view->itemsize != sizeof(double) || view->format == NULL || strcmp(view->format, "d") != 0 || view->ndim != 2
        || view->shape[0] != n || view->shape[1] != n) {
        PyErr_Format(PyExc_TypeError, "%s: %s must be a %zd x %zd float64 matrix", function, name, n, n);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

/* The ``count`` numbers args[0 .. count - 1] as doubles into out, or -1 with the error set. */
static int
take_doubles(PyObject *const *args, int count, double *out)
{
    for (int k = 0; k < count; k++) {
        out[k] = PyFloat_AsDouble(args[k]);
        if (out[k] == -1.0 && PyErr_Occurred()) {
            return -1;
        }
    }
    return 0;
}

/* torque_advance(x, v, x_law, v_law, expected_deg, expected_dps, lag, a, target, dt): ExpectedTracking.advance of
   the torque model with an inertia known: the law's state is the model's before the step (x_law = x, v_law = v);
   torque_step's step when dt > 0; the expectation is the state (expected_deg = x, expected_dps = v); lag = target - x.
   In place. */
static PyObject *
torque_advance(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    static const char *names[] = {"x", "v", "x_law", "v_law", "expected_deg", "expected_dps", "lag", "a", "target"};
    Py_buffer views[9];
    Py_ssize_t n;
    if (take_arrays("torque_advance", args, nargs, 10, names, 7, 9, views, &n) < 0) {
        return NULL;
    }
    double dt = PyFloat_AsDouble(args[9]);
    if (dt == -1.0 && PyErr_Occurred()) {
        release_arrays(views, 9);
        return NULL;
    }
    double *x = views[0].buf, *v = views[1].buf, *x_law = views[2].buf, *v_law = views[3].buf;
    double *expected_deg = views[4].buf, *expected_dps = views[5].buf, *lag = views[6].buf;
    const double *a = views[7].buf, *target = views[8].buf;
    double half_dt2 = 0.5 * dt * dt;
    for (Py_ssize_t i = 0; i < n; i++) {
        x_law[i] = x[i];
        v_law[i] = v[i];
        if (dt > 0.0) {
            double xi = x[i] + v[i] * dt;
            x[i] = xi + a[i] * half_dt2;
            v[i] = v[i] + a[i] * dt;
        }
        expected_deg[i] = x[i];
        expected_dps[i] = v[i];
        lag[i] = target[i] - x[i];
    }
    release_arrays(views, 9);
    Py_RETURN_NONE;
}

#define LAW_ARRAYS 14

/* torque_law(accel, tau, target, ref_v, ref_a, reference_deg, reference_dps, reference_dps2, kp, x_law, kd, v_law, lo,
   hi, mass_inv, mass, rad_per_deg, deg_per_rad): ExpectedTracking.command's torque-mode part, in place. The reference
   is taken (target, ref_v, ref_a = reference_*); tau = kp (target - x_law) + (ref_v - v_law) kd, plus mass . (ref_a
   rad_per_deg) where mass is not None (the feed-forward covers the inertia), clipped to [lo, hi]; accel = (mass_inv .
   tau) deg_per_rad. The matrix products sum in index order, a BLAS in its own: their last bits may differ from numpy's
   np.dot (as they do between BLAS builds). */
static PyObject *
torque_law(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    static const char *names[LAW_ARRAYS] = {"accel", "tau", "target", "ref_v", "ref_a", "reference_deg",
                                            "reference_dps", "reference_dps2", "kp", "x_law", "kd", "v_law", "lo",
                                            "hi"};
    Py_buffer views[LAW_ARRAYS + 2];
    Py_ssize_t n;
    if (take_arrays("torque_law", args, nargs, LAW_ARRAYS + 4, names, 5, LAW_ARRAYS, views, &n) < 0) {
        return NULL;
    }
    int taken = LAW_ARRAYS;
    PyObject *result = NULL;
    if (take_matrix("torque_law", args[LAW_ARRAYS], &views[taken], "mass_inv", n) < 0) {
        goto done;
    }
    taken++;
    const double *mass = NULL;
    if (args[LAW_ARRAYS + 1] != Py_None) {
        if (take_matrix("torque_law", args[LAW_ARRAYS + 1], &views[taken], "mass", n) < 0) {
            goto done;
        }
        mass = views[taken].buf;
        taken++;
    }
    double factors[2];  /* rad_per_deg, deg_per_rad */
    if (take_doubles(args + LAW_ARRAYS + 2, 2, factors) < 0) {
        goto done;
    }
    const double rad_per_deg = factors[0], deg_per_rad = factors[1];
    double *accel = views[0].buf, *tau = views[1].buf, *target = views[2].buf, *ref_v = views[3].buf;
    double *ref_a = views[4].buf;
    const double *reference_deg = views[5].buf, *reference_dps = views[6].buf, *reference_dps2 = views[7].buf;
    const double *kp = views[8].buf, *x_law = views[9].buf, *kd = views[10].buf, *v_law = views[11].buf;
    const double *lo = views[12].buf, *hi = views[13].buf;
    const double *mass_inv = views[LAW_ARRAYS].buf;
    for (Py_ssize_t i = 0; i < n; i++) {
        target[i] = reference_deg[i];
        ref_v[i] = reference_dps[i];
        ref_a[i] = reference_dps2[i];
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        double p = kp[i] * (target[i] - x_law[i]);
        double d = (ref_v[i] - v_law[i]) * kd[i];
        double t = p + d;
        if (mass != NULL) {
            const double *row = mass + i * n;
            double w = row[0] * (ref_a[0] * rad_per_deg);
            for (Py_ssize_t j = 1; j < n; j++) {
                w += row[j] * (ref_a[j] * rad_per_deg);
            }
            t += w;
        }
        tau[i] = np_maximum(np_minimum(t, hi[i]), lo[i]);
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        const double *row = mass_inv + i * n;
        double s = row[0] * tau[0];
        for (Py_ssize_t j = 1; j < n; j++) {
            s += row[j] * tau[j];
        }
        accel[i] = s * deg_per_rad;
    }
    result = Py_NewRef(Py_None);
done:
    release_arrays(views, taken);
    return result;
}

/* Python's round() of a float (half to even) as a float: CPython's own steps, whatever the rounding mode, and a
   zero without a sign (round() gives the int 0; C's round(-0.3) gives -0.0, which + 0.0 makes 0.0). */
static inline double
round_half_even(double x)
{
    double rounded = round(x);
    if (fabs(x - rounded) == 0.5) {
        rounded = 2.0 * round(x / 2.0);
    }
    return rounded + 0.0;
}

#define CURRENT_ARRAYS 4

/* torque_currents(amps, torque, nm_per_a, raw_limit, limited, addend, raw_per_a, amps_num, amps_den): the
   torque-current set-points of joint torques, in place: torque += addend where addend is not None (the feed-forward);
   raw = round(torque / nm_per_a * raw_per_a) (half to even), limited to +-raw_limit (limited marks where); amps = raw *
   amps_num / amps_den (exact integers in doubles: Python's int arithmetic and true division give the same float).
   ArmTransmission.iq_raw_limited_list and iq_amps in one. Returns None, or the index of the first joint
   whose current is not a finite number (then nothing but the torque has changed: the caller raises). */
static PyObject *
torque_currents(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    static const char *names[CURRENT_ARRAYS] = {"amps", "torque", "nm_per_a", "raw_limit"};
    Py_buffer views[CURRENT_ARRAYS + 2];
    Py_ssize_t n;
    if (take_arrays("torque_currents", args, nargs, CURRENT_ARRAYS + 5, names, 2, CURRENT_ARRAYS, views, &n) < 0) {
        return NULL;
    }
    int taken = CURRENT_ARRAYS;
    PyObject *result = NULL;
    Py_ssize_t m = n;
    if (take_buffer("torque_currents", args[CURRENT_ARRAYS], &views[taken], 1, KIND_BOOL, "limited", &m) < 0) {
        goto done;
    }
    taken++;
    const double *addend = NULL;
    if (args[CURRENT_ARRAYS + 1] != Py_None) {
        if (take_array("torque_currents", args[CURRENT_ARRAYS + 1], &views[taken], 0, "addend", &m) < 0) {
            goto done;
        }
        addend = views[taken].buf;
        taken++;
    }
    double scales[3];  /* raw_per_a, amps_num, amps_den */
    if (take_doubles(args + CURRENT_ARRAYS + 2, 3, scales) < 0) {
        goto done;
    }
    const double raw_per_a = scales[0], amps_num = scales[1], amps_den = scales[2];
    double *amps = views[0].buf, *torque = views[1].buf;
    const double *nm_per_a = views[2].buf, *raw_limit = views[3].buf;
    unsigned char *limited = views[CURRENT_ARRAYS].buf;
    if (addend != NULL) {
        for (Py_ssize_t i = 0; i < n; i++) {
            torque[i] = torque[i] + addend[i];
        }
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        if (!isfinite(torque[i] / nm_per_a[i] * raw_per_a)) {
            result = PyLong_FromSsize_t(i);
            goto done;
        }
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        double raw = round_half_even(torque[i] / nm_per_a[i] * raw_per_a);
        unsigned char over = 1;
        if (raw > raw_limit[i]) {
            raw = raw_limit[i];
        }
        else if (raw < -raw_limit[i]) {
            raw = 0.0 - raw_limit[i];  /* (not -raw_limit: a limit of 0 would give -0.0, Python's int -0 is 0) */
        }
        else {
            over = 0;
        }
        limited[i] = over;
        amps[i] = raw * amps_num / amps_den;
    }
    result = Py_NewRef(Py_None);
done:
    release_arrays(views, taken);
    return result;
}

/* gather_scaled(out, src, order, factor): out[i] = src[order[i]] * factor, order an int64 array of indices of src
   (numpy's src[order] then deg2rad for factor pi / 180: the same float64s). */
static PyObject *
gather_scaled(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    static const char *names[] = {"out", "src"};
    Py_buffer views[3];
    Py_ssize_t n;
    if (take_arrays("gather_scaled", args, nargs, 4, names, 1, 2, views, &n) < 0) {
        return NULL;
    }
    PyObject *result = NULL;
    Py_ssize_t m = n;
    if (take_buffer("gather_scaled", args[2], &views[2], 0, KIND_INT64, "order", &m) < 0) {
        release_arrays(views, 2);
        return NULL;
    }
    double factor = PyFloat_AsDouble(args[3]);
    if (factor == -1.0 && PyErr_Occurred()) {
        goto done;
    }
    const int64_t *order = views[2].buf;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (order[i] < 0 || order[i] >= n) {
            PyErr_Format(PyExc_ValueError, "gather_scaled: order[%zd] = %lld is not an index of src", i,
                         (long long)order[i]);
            goto done;
        }
    }
    double *out = views[0].buf;
    const double *src = views[1].buf;
    if (out == src) {
        PyErr_SetString(PyExc_ValueError, "gather_scaled: out must not be src");
        goto done;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        out[i] = src[order[i]] * factor;
    }
    result = Py_NewRef(Py_None);
done:
    release_arrays(views, 3);
    return result;
}

/* stack_rows(out, rows): out[r, :] = rows[r] for a (k, n) float64 matrix and k one-dimensional arrays of n float64 or
   bool (as 0.0 / 1.0): numpy's array(rows, dtype=float64) into out. */
static PyObject *
stack_rows(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    if (nargs != 2) {
        PyErr_Format(PyExc_TypeError, "stack_rows takes 2 positional arguments, got %zd", nargs);
        return NULL;
    }
    Py_buffer out;
    if (PyObject_GetBuffer(args[0], &out, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) {
        PyErr_SetString(PyExc_TypeError, "stack_rows: out must be a C-contiguous, writable float64 matrix");
        return NULL;
    }
    PyObject *rows = args[1];
    PyObject *result = NULL;
    if (out.itemsize != sizeof(double) || out.format == NULL || strcmp(out.format, "d") != 0 || out.ndim != 2) {
        PyErr_SetString(PyExc_TypeError, "stack_rows: out must be a two-dimensional float64 matrix");
        goto done;
    }
    Py_ssize_t k = out.shape[0], n = out.shape[1];
    if (!PyTuple_Check(rows) || PyTuple_GET_SIZE(rows) != k) {
        PyErr_Format(PyExc_TypeError, "stack_rows: rows must be a tuple of %zd arrays", k);
        goto done;
    }
    double *target = out.buf;
    for (Py_ssize_t r = 0; r < k; r++) {
        Py_buffer row;
        if (PyObject_GetBuffer(PyTuple_GET_ITEM(rows, r), &row, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
            PyErr_Format(PyExc_TypeError, "stack_rows: row %zd must be a C-contiguous array", r);
            goto done;
        }
        int is_double = holds(&row, KIND_FLOAT64);
        if ((!is_double && !holds(&row, KIND_BOOL)) || row.len / row.itemsize != n) {
            PyErr_Format(PyExc_TypeError, "stack_rows: row %zd must be a one-dimensional float64 or bool array of %zd "
                         "entries", r, n);
            PyBuffer_Release(&row);
            goto done;
        }
        double *line = target + r * n;
        if (is_double) {
            memcpy(line, row.buf, (size_t)n * sizeof(double));
        }
        else {
            const unsigned char *flags = row.buf;
            for (Py_ssize_t i = 0; i < n; i++) {
                line[i] = flags[i] ? 1.0 : 0.0;
            }
        }
        PyBuffer_Release(&row);
    }
    result = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&out);
    return result;
}

/* ------------------------------------------------------------------------------------------- the axes' replies */

/* StateAbsorber(index, state_type, encoder, motor_deg, speed_dps, iq_a, temperature_c, last_reply_s, q_deg, qd_dps,
   fresh, counts, direction, gear, offset): the C twin of AxisStates.absorb's loop (motion.control.axes), for drives
   whose motion replies carry the encoder. It holds the axes' arrays (changed in place only, never replaced: their
   buffers are held for its life) and their per-axis terms: counts per revolution and the transmission's direction,
   gear ratio and zero offset. A call absorber(replies, start, keep_fresh) takes replies[start:] (a list or tuple of
   Reply tuples: motor id, request, message, time) as the Python loop does, with the same operations in the same order
   (Python's int and float arithmetic in int64 and double: the same values), and returns -1, or the position of the
   first reply it leaves to the Python loop (one not a 4-tuple, or a motion reply whose fields are not plain ints and
   floats): the caller takes that one and calls again from the next. Unless keep_fresh, fresh is cleared first. */

#define ABSORB_WRITABLE 9
#define ABSORB_ARRAYS 13
#define ENCODER_MAX (1LL << 52)

typedef struct {
    PyObject_HEAD
    PyObject *index;
    PyObject *state_type;
    PyObject *arrays[ABSORB_ARRAYS];
    Py_buffer views[ABSORB_ARRAYS];
    int held;
    Py_ssize_t n;
    vectorcallfunc vectorcall;
} StateAbsorber;

static PyObject *absorb_names[4];  /* encoder, speed_dps, iq_a, temperature_c (interned at import) */

static void
absorber_release(StateAbsorber *a)
{
    for (int i = 0; i < a->held; i++) {
        PyBuffer_Release(&a->views[i]);
    }
    a->held = 0;
}

#define ABSORBER_REFERENCES(APPLY, a)           \
    APPLY((a)->index);                          \
    APPLY((a)->state_type);                     \
    for (int k = 0; k < ABSORB_ARRAYS; k++) {   \
        APPLY((a)->arrays[k]);                  \
    }

static int
absorber_traverse(PyObject *self, visitproc visit, void *arg)
{
    ABSORBER_REFERENCES(Py_VISIT, (StateAbsorber *)self)
    return 0;
}

static int
absorber_clear(PyObject *self)
{
    absorber_release((StateAbsorber *)self);  /* (the buffers before the arrays they belong to) */
    ABSORBER_REFERENCES(Py_CLEAR, (StateAbsorber *)self)
    return 0;
}

static void
absorber_dealloc(PyObject *self)
{
    PyObject_GC_UnTrack(self);
    absorber_clear(self);
    Py_TYPE(self)->tp_free(self);
}

/* A plain int or float as a double (1), anything else 0 (the Python loop takes it); -1 with an error set. */
static int
plain_number(PyObject *value, double *out)
{
    if (PyFloat_CheckExact(value)) {
        *out = PyFloat_AS_DOUBLE(value);
        return 1;
    }
    if (PyLong_CheckExact(value)) {
        *out = PyLong_AsDouble(value);
        if (*out == -1.0 && PyErr_Occurred()) {
            if (!PyErr_ExceptionMatches(PyExc_OverflowError)) {
                return -1;
            }
            PyErr_Clear();
            return 0;
        }
        return 1;
    }
    return 0;
}

/* One motion reply of axis i: 1 taken, 0 left to the Python loop (nothing written), -1 error. */
static int
absorb_state(StateAbsorber *a, Py_ssize_t i, PyObject *state, PyObject *received)
{
    if (!PyFloat_CheckExact(received)) {
        return 0;
    }
    PyObject *values[4] = {NULL, NULL, NULL, NULL};
    int result = -1;
    for (int k = 0; k < 4; k++) {
        values[k] = PyObject_GetAttr(state, absorb_names[k]);
        if (values[k] == NULL) {
            goto done;
        }
    }
    /* The encoder, a plain int of at most 52 bits (the difference is exact as a double), and the other fields'
       numbers. */
    result = 0;
    if (!PyLong_CheckExact(values[0])) {
        goto done;
    }
    int overflow = 0;
    long long encoder = PyLong_AsLongLongAndOverflow(values[0], &overflow);
    if (encoder == -1 && PyErr_Occurred()) {
        result = -1;
        goto done;
    }
    if (overflow || encoder > ENCODER_MAX || encoder < -ENCODER_MAX) {
        goto done;
    }
    double speed, iq, temperature;
    int ok;
    if ((ok = plain_number(values[1], &speed)) != 1 || (ok = plain_number(values[2], &iq)) != 1
        || (ok = plain_number(values[3], &temperature)) != 1) {
        result = ok;
        goto done;
    }
    int64_t *encoders = a->views[0].buf;
    double *motor_degs = a->views[1].buf, *speeds = a->views[2].buf, *iqs = a->views[3].buf;
    double *temperatures = a->views[4].buf, *last_reply_s = a->views[5].buf, *q_deg = a->views[6].buf;
    double *qd_dps = a->views[7].buf;
    unsigned char *fresh = a->views[8].buf;
    const double counts = ((const double *)a->views[9].buf)[i], direction = ((const double *)a->views[10].buf)[i];
    const double gear = ((const double *)a->views[11].buf)[i], offset = ((const double *)a->views[12].buf)[i];
    long long previous = encoders[i];
    if (previous > ENCODER_MAX || previous < -ENCODER_MAX) {
        goto done;
    }
    long long delta = encoder - previous;
    if ((double)delta > counts / 2) {
        delta -= (long long)counts;
    }
    else if ((double)delta < -counts / 2) {
        delta += (long long)counts;
    }
    encoders[i] = encoder;
    double motor_deg = motor_degs[i] + (double)delta * 360.0 / counts;
    motor_degs[i] = motor_deg;
    speeds[i] = speed;
    iqs[i] = iq;
    temperatures[i] = temperature;
    last_reply_s[i] = PyFloat_AS_DOUBLE(received);
    fresh[i] = 1;
    q_deg[i] = direction * motor_deg / gear + offset;
    qd_dps[i] = direction * speed / gear;
    result = 1;
done:
    for (int k = 0; k < 4; k++) {
        Py_XDECREF(values[k]);
    }
    return result;
}

/* One Reply tuple, in the Python loop's order of checks: its motor's axis (none: skipped), a time (None: skipped), a
   motion reply (anything else: skipped), then absorb_state. 1 taken or skipped, 0 left to the Python loop, -1 error. */
static int
absorb_reply(StateAbsorber *a, PyObject *reply)
{
    PyObject *axis = PyDict_GetItemWithError(a->index, PyTuple_GET_ITEM(reply, 0));
    if (axis == NULL) {
        return PyErr_Occurred() ? -1 : 1;
    }
    Py_ssize_t i = PyLong_AsSsize_t(axis);
    if (i == -1 && PyErr_Occurred()) {
        return -1;
    }
    if (i < 0 || i >= a->n) {
        PyErr_Format(PyExc_ValueError, "StateAbsorber: axis index %zd out of range", i);
        return -1;
    }
    PyObject *state = PyTuple_GET_ITEM(reply, 2), *received = PyTuple_GET_ITEM(reply, 3);
    if (received == Py_None) {
        return 1;
    }
    int is_state = PyObject_IsInstance(state, a->state_type);
    if (is_state <= 0) {
        return is_state < 0 ? -1 : 1;
    }
    return absorb_state(a, i, state, received);
}

static PyObject *
absorber_call(PyObject *self, PyObject *const *args, size_t nargsf, PyObject *kwnames)
{
    StateAbsorber *a = (StateAbsorber *)self;
    Py_ssize_t nargs = PyVectorcall_NARGS(nargsf);
    if (kwnames != NULL || nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "StateAbsorber takes 3 positional arguments (replies, start, keep_fresh)");
        return NULL;
    }
    if (a->held != ABSORB_ARRAYS) {
        PyErr_SetString(PyExc_ValueError, "StateAbsorber: cleared");
        return NULL;
    }
    PyObject *replies = args[0];
    if (!PyList_Check(replies) && !PyTuple_Check(replies)) {
        PyErr_SetString(PyExc_TypeError, "StateAbsorber: replies must be a list or a tuple");
        return NULL;
    }
    Py_ssize_t start = PyLong_AsSsize_t(args[1]);
    if (start == -1 && PyErr_Occurred()) {
        return NULL;
    }
    int keep_fresh = PyObject_IsTrue(args[2]);
    if (keep_fresh < 0) {
        return NULL;
    }
    if (!keep_fresh) {
        memset(a->views[8].buf, 0, (size_t)a->n);
    }
    for (Py_ssize_t k = start < 0 ? 0 : start; k < PySequence_Fast_GET_SIZE(replies); k++) {
        PyObject *reply = PySequence_Fast_GET_ITEM(replies, k);
        if (!PyTuple_Check(reply) || PyTuple_GET_SIZE(reply) != 4) {
            return PyLong_FromSsize_t(k);
        }
        Py_INCREF(reply);  /* (held while Python code may run: a property, an __instancecheck__) */
        int taken = absorb_reply(a, reply);
        Py_DECREF(reply);
        if (taken < 0) {
            return NULL;
        }
        if (taken == 0) {
            return PyLong_FromSsize_t(k);
        }
    }
    return PyLong_FromLong(-1);
}

static PyObject *
absorber_new(PyTypeObject *type, PyObject *args, PyObject *kwargs)
{
    if (kwargs != NULL && PyDict_GET_SIZE(kwargs) != 0) {
        PyErr_SetString(PyExc_TypeError, "StateAbsorber takes positional arguments only");
        return NULL;
    }
    if (!PyTuple_Check(args) || PyTuple_GET_SIZE(args) != 2 + ABSORB_ARRAYS) {
        PyErr_Format(PyExc_TypeError, "StateAbsorber takes %d arguments (index, state_type, and %d arrays)",
                     2 + ABSORB_ARRAYS, ABSORB_ARRAYS);
        return NULL;
    }
    PyObject *index = PyTuple_GET_ITEM(args, 0), *state_type = PyTuple_GET_ITEM(args, 1);
    if (!PyDict_Check(index) || !PyType_Check(state_type)) {
        PyErr_SetString(PyExc_TypeError, "StateAbsorber: index must be a dict and state_type a class");
        return NULL;
    }
    StateAbsorber *a = (StateAbsorber *)type->tp_alloc(type, 0);
    if (a == NULL) {
        return NULL;
    }
    a->vectorcall = absorber_call;
    a->index = Py_NewRef(index);
    a->state_type = Py_NewRef(state_type);
    static const char *names[ABSORB_ARRAYS] = {"encoder", "motor_deg", "speed_dps", "iq_a", "temperature_c",
                                               "last_reply_s", "q_deg", "qd_dps", "fresh", "counts", "direction",
                                               "gear", "offset"};
    Py_ssize_t n = -1;
    for (int k = 0; k < ABSORB_ARRAYS; k++) {
        PyObject *array = PyTuple_GET_ITEM(args, 2 + k);
        a->arrays[k] = Py_NewRef(array);
        Py_buffer *view = &a->views[k];
        BufferKind kind = k == 0 ? KIND_INT64 : k == 8 ? KIND_BOOL : KIND_FLOAT64;  /* encoders, fresh marks */
        if (take_buffer("StateAbsorber", array, view, k < ABSORB_WRITABLE, kind, names[k], &n) < 0) {
            goto fail;
        }
        a->held++;
    }
    a->n = n;
    return (PyObject *)a;
fail:
    Py_DECREF(a);
    return NULL;
}

static PyTypeObject StateAbsorberType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "motion._speedups.StateAbsorber",
    .tp_doc = PyDoc_STR("StateAbsorber(index, state_type, encoder, motor_deg, speed_dps, iq_a, temperature_c, "
                        "last_reply_s, q_deg, qd_dps, fresh, counts, direction, gear, offset): AxisStates.absorb's "
                        "loop in C; call (replies, start, keep_fresh) -> -1 or the reply left to Python"),
    .tp_basicsize = sizeof(StateAbsorber),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC | Py_TPFLAGS_HAVE_VECTORCALL,
    .tp_new = absorber_new,
    .tp_dealloc = absorber_dealloc,
    .tp_traverse = absorber_traverse,
    .tp_clear = absorber_clear,
    .tp_call = PyVectorcall_Call,
    .tp_vectorcall_offset = offsetof(StateAbsorber, vectorcall),
};

static PyMethodDef speedups_methods[] = {
    {"chase", (PyCFunction)(void (*)(void))chase, METH_FASTCALL,
     PyDoc_STR("chase(x, v, dt, target, cap, gain, accel, max_step): motion.control.tracking.chase in C, in place.")},
    {"torque_pd", (PyCFunction)(void (*)(void))torque_pd, METH_FASTCALL,
     PyDoc_STR("torque_pd(tau, kp, target, x, kd, ref_v, v): tau = kp (target - x) + (ref_v - v) kd, in place.")},
    {"moved_beyond", (PyCFunction)(void (*)(void))moved_beyond, METH_FASTCALL,
     PyDoc_STR("moved_beyond(a, b, limit): abs(a - b).max() > limit, as numpy gives it.")},
    {"torque_advance", (PyCFunction)(void (*)(void))torque_advance, METH_FASTCALL,
     PyDoc_STR("torque_advance(x, v, x_law, v_law, expected_deg, expected_dps, lag, a, target, dt): the torque "
               "model's advance, in place.")},
    {"torque_law", (PyCFunction)(void (*)(void))torque_law, METH_FASTCALL,
     PyDoc_STR("torque_law(accel, tau, target, ref_v, ref_a, reference_deg, reference_dps, reference_dps2, kp, x_law, "
               "kd, v_law, lo, hi, mass_inv, mass, rad_per_deg, deg_per_rad): the torque model's command, in place.")},
    {"gather_scaled", (PyCFunction)(void (*)(void))gather_scaled, METH_FASTCALL,
     PyDoc_STR("gather_scaled(out, src, order, factor): out[i] = src[order[i]] * factor.")},
    {"stack_rows", (PyCFunction)(void (*)(void))stack_rows, METH_FASTCALL,
     PyDoc_STR("stack_rows(out, rows): out[r, :] = rows[r] (float64 or bool rows), numpy's array(rows) into out.")},
    {"torque_currents", (PyCFunction)(void (*)(void))torque_currents, METH_FASTCALL,
     PyDoc_STR("torque_currents(amps, torque, nm_per_a, raw_limit, limited, addend, raw_per_a, amps_num, amps_den): the "
               "limited torque currents, in place; None or the first joint whose current is not finite.")},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef speedups_module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "motion._speedups",
    .m_doc = PyDoc_STR("The optional C accelerator of the hot path: SlotBuilder (frozen_builder) and chase."),
    .m_size = -1,
    .m_methods = speedups_methods,
};

PyMODINIT_FUNC
PyInit__speedups(void)
{
    PyObject *module = PyModule_Create(&speedups_module);
    if (module == NULL) {
        return NULL;
    }
    /* What the Python side expects (motion.protocol.compiled.SPEEDUPS_ABI): a module built from an older source
       (an editable install not reinstalled) is then not used, rather than half used. Raise it with any change of what
       the module offers. */
    if (PyModule_AddIntConstant(module, "ABI", 4) < 0) {
        Py_DECREF(module);
        return NULL;
    }
    const char *fields[] = {"encoder", "speed_dps", "iq_a", "temperature_c"};
    for (int k = 0; k < 4; k++) {
        absorb_names[k] = PyUnicode_InternFromString(fields[k]);
        if (absorb_names[k] == NULL) {
            Py_DECREF(module);
            return NULL;
        }
    }
    PyTypeObject *types[] = {&SlotBuilderType, &CLayoutType, &CanRequestEncoderType, &CanReplyDecoderType,
                             &StateAbsorberType};
    const char *names[] = {"SlotBuilder", "CLayout", "CanRequestEncoder", "CanReplyDecoder", "StateAbsorber"};
    for (size_t i = 0; i < sizeof(types) / sizeof(types[0]); i++) {
        if (PyType_Ready(types[i]) < 0 || PyModule_AddObjectRef(module, names[i], (PyObject *)types[i]) < 0) {
            Py_DECREF(module);
            return NULL;
        }
    }
    return module;
}
