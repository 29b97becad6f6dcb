// The wire format of scalesteer (see docs/protocol.md): msgpack maps tagged by `type`, arrays as
// {dtype, shape, data} holding raw little-endian bytes. Decoding checks dtype, shape and byte
// length against each other before anything is allocated.

import { decode as unpack, encode as pack } from "@msgpack/msgpack";

export const PROTOCOL_VERSION = "1.7";

/** Array dtypes the protocol allows: typed-array constructor and item size in bytes. */
export const DTYPES = Object.freeze({
  "<f4": { ctor: Float32Array, size: 4 },
  "<f8": { ctor: Float64Array, size: 8 },
  "<i4": { ctor: Int32Array, size: 4 },
  "<i8": { ctor: BigInt64Array, size: 8 },
  "<u4": { ctor: Uint32Array, size: 4 },
  "<u2": { ctor: Uint16Array, size: 2 },
  "|u1": { ctor: Uint8Array, size: 1 },
});

/** Array fields of each message type: the dtype and rank the protocol fixes for them. */
export const ARRAY_FIELDS = Object.freeze({
  topology: {
    residue_ids: ["<i4", 1],
    bonds: ["<i4", 2],
    radii: ["<f4", 1],
    charges: ["<f4", 1],
    bfactors: ["<f4", 1],
  },
  frame: { positions: ["<f4", 2], box: ["<f4", 2], velocities: ["<f4", 2] },
  forces: { indices: ["<i4", 1], forces: ["<f4", 2] },
  image: { histogram: ["<f4", 1] },
});

const LITTLE_ENDIAN = new Uint8Array(new Uint16Array([1]).buffer)[0] === 1;
const MAX_SEQ = 2 ** 53;

/** A malformed message: `code` is a protocol error code, `path` names the field. */
export class WireError extends Error {
  constructor(code, message, path = "") {
    super(message);
    this.name = "WireError";
    this.code = code;
    this.path = path;
  }
}

/** A decoded wire array: dtype, shape and the flat values as a typed array. */
export class WireArray {
  constructor(dtype, shape, values) {
    this.dtype = dtype;
    this.shape = shape;
    this.values = values;
  }

  get count() {
    return this.shape.length ? this.shape[0] : 0;
  }

  /** Encodable form: {dtype, shape, data: little-endian bytes}. */
  toWire() {
    const { size } = DTYPES[this.dtype];
    const bytes = new Uint8Array(this.values.buffer, this.values.byteOffset, this.values.length * size);
    return { dtype: this.dtype, shape: [...this.shape], data: LITTLE_ENDIAN ? bytes : swapBytes(bytes, size) };
  }

  static from(values, dtype, shape = [values.length]) {
    const spec = DTYPES[dtype];
    if (!spec) throw new WireError("invalid_message", `dtype ${dtype} is not allowed`);
    const typed = values instanceof spec.ctor ? values : spec.ctor.from(values);
    if (shape.reduce((a, b) => a * b, 1) !== typed.length) {
      throw new WireError("invalid_message", `shape [${shape}] does not hold ${typed.length} values`);
    }
    return new WireArray(dtype, shape, typed);
  }
}

function swapBytes(bytes, size) {
  const out = new Uint8Array(bytes.length);
  for (let i = 0; i < bytes.length; i += size) {
    for (let k = 0; k < size; k++) out[i + k] = bytes[i + size - 1 - k];
  }
  return out;
}

/**
 * Check and convert one `{dtype, shape, data}` map. `expect` = [dtype, rank] from ARRAY_FIELDS;
 * `maxElements` bounds the declared shape before any allocation.
 */
export function decodeArray(obj, path, expect = null, maxElements = 1 << 28) {
  if (obj === null || typeof obj !== "object" || Array.isArray(obj) || obj instanceof Uint8Array) {
    throw new WireError("invalid_message", `${path}: an array must be a map {dtype, shape, data}`, path);
  }
  const { dtype, shape, data } = obj;
  const spec = DTYPES[dtype];
  if (!spec) throw new WireError("invalid_message", `${path}: dtype ${String(dtype)} is not allowed`, path);
  if (expect && dtype !== expect[0]) {
    throw new WireError("invalid_message", `${path}: dtype must be ${expect[0]}, got ${dtype}`, path);
  }
  if (!Array.isArray(shape) || !shape.every((n) => Number.isInteger(n) && n >= 0)) {
    throw new WireError("invalid_message", `${path}: shape must be a list of non-negative integers`, path);
  }
  if (expect && shape.length !== expect[1]) {
    throw new WireError("invalid_message", `${path}: rank must be ${expect[1]}, got ${shape.length}`, path);
  }
  const count = shape.reduce((a, b) => a * b, 1);
  if (count > maxElements) {
    throw new WireError("too_large", `${path}: ${count} elements exceed the limit of ${maxElements}`, path);
  }
  if (!(data instanceof Uint8Array)) {
    throw new WireError("invalid_message", `${path}: data must be binary`, path);
  }
  if (data.byteLength !== count * spec.size) {
    throw new WireError(
      "invalid_message",
      `${path}: ${data.byteLength} bytes do not match shape [${shape}] of ${dtype}`,
      path,
    );
  }
  // copy into a fresh, aligned buffer (msgpack hands out views into the message)
  const copy = new Uint8Array(data.byteLength);
  copy.set(LITTLE_ENDIAN ? data : swapBytes(data, spec.size));
  return new WireArray(dtype, [...shape], new spec.ctor(copy.buffer, 0, count));
}

/** Decode one binary frame into a message object; throws WireError on anything malformed. */
export function decodeMessage(raw, { maxBytes = 1 << 30, maxElements = 1 << 28 } = {}) {
  const bytes = raw instanceof Uint8Array ? raw : new Uint8Array(raw);
  if (bytes.byteLength > maxBytes) {
    throw new WireError("too_large", `message of ${bytes.byteLength} bytes exceeds ${maxBytes}`);
  }
  let obj;
  try {
    obj = unpack(bytes, { useBigInt64: false });
  } catch (err) {
    throw new WireError("invalid_message", `not valid msgpack: ${err.message}`);
  }
  if (obj === null || typeof obj !== "object" || Array.isArray(obj) || obj instanceof Uint8Array) {
    throw new WireError("invalid_message", "message must be a map");
  }
  if (typeof obj.type !== "string") {
    throw new WireError("invalid_message", "message has no string field type", "type");
  }
  for (const key of ["seq", "ref"]) {
    if (
      obj[key] !== undefined &&
      obj[key] !== null &&
      !(Number.isInteger(obj[key]) && obj[key] >= 0 && obj[key] < MAX_SEQ)
    ) {
      throw new WireError(
        "invalid_message",
        `${obj.type}.${key} must be an integer in [0, 2^53)`,
        `${obj.type}.${key}`,
      );
    }
  }
  const arrays = ARRAY_FIELDS[obj.type];
  if (arrays) {
    for (const [field, expect] of Object.entries(arrays)) {
      if (obj[field] !== undefined && obj[field] !== null) {
        obj[field] = decodeArray(obj[field], `${obj.type}.${field}`, expect, maxElements);
      }
    }
  }
  return obj;
}

function stripForWire(value) {
  if (value instanceof WireArray) return value.toWire();
  if (value === null || typeof value !== "object" || value instanceof Uint8Array) return value;
  if (Array.isArray(value)) return value.map(stripForWire);
  const out = {};
  for (const [k, v] of Object.entries(value)) {
    if (v !== undefined && v !== null) out[k] = stripForWire(v);
  }
  return out;
}

/** Encode a message object; null and undefined fields are omitted (the default applies). */
export function encodeMessage(message) {
  if (!message || typeof message.type !== "string") {
    throw new WireError("invalid_message", "a message needs a string field type");
  }
  return pack(stripForWire(message));
}
